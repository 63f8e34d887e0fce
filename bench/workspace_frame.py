"""Draw the workspace frame task files use: docs/workspace_frame.png.

    MUJOCO_GL=egl python bench/workspace_frame.py [--out docs/workspace_frame.png]

A task file's `region`s, `[[camera]]` positions and `[[region]]`s are metres from the
workspace centre on the table top, with the world's axes: +x away from the robot's base,
+y to the robot's left, z up (the Panda's centre is 0.55 reach in front of its base).
The picture is the lift scene seen straight down from 20 m through a narrow lens (the base at
the bottom, +x up the image, +y to the left), with the centre, the +x and +y arrows and
lift's cube region drawn on it. Before drawing, two marker spheres are rendered at
(+0.1, 0) and (0, +0.1) in the workspace frame and found in the image: the script stops
if either lands more than 2 px from where the drawing puts that point.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import mujoco
import numpy as np

from scenes import build_scene

ROOT = Path(__file__).resolve().parent.parent
SIZE = (720, 720)  # px, height and width
MARK_RGBA = (1.0, 0.0, 1.0, 1.0)  # pure magenta: no other pixel of the scene is that colour


class TopView:
    """A camera far above the table looking straight down through a narrow lens (nearly orthographic).

    Maps world (x, y, z) to image pixels (column, row) exactly, as a pinhole: +x is up the image, +y to the left.
    """

    def __init__(self, model: mujoco.MjModel, look_at: tuple[float, float], extent: float, height: float = 20.0) -> None:
        model.vis.global_.fovy = float(np.degrees(2 * np.arctan(extent / 2 / height)))  # `extent` m tall at the table
        model.vis.global_.offheight, model.vis.global_.offwidth = SIZE
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        self.camera.lookat[:] = (look_at[0], look_at[1], 0.0)
        self.camera.distance, self.camera.azimuth, self.camera.elevation = height, 0.0, -90.0  # image up = +x
        self.look_at, self.height = np.array(look_at), height
        self.focal_px = SIZE[0] / extent * height  # px per m at the table, times the height

    def pixel(self, xy: np.ndarray, z: float = 0.0) -> np.ndarray:
        """Column and row of the world point (x, y, z), as pixel indices (imshow's coordinates): +x is up, +y left."""
        d = (np.asarray(xy, float) - self.look_at) * self.focal_px / (self.height - z)
        return np.array([SIZE[1] / 2 - d[1], SIZE[0] / 2 - d[0]]) - 0.5  # pixel i spans [i, i + 1) of the image plane


def render(model: mujoco.MjModel, data: mujoco.MjData, view: TopView, marks: list[np.ndarray]) -> np.ndarray:
    """The top view, with a magenta sphere at each world point in `marks` (lit as emission: one flat colour)."""
    with mujoco.Renderer(model, *SIZE) as renderer:
        renderer.update_scene(data, view.camera)
        scene = renderer.scene
        for point in marks:
            geom = scene.geoms[scene.ngeom]
            mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_SPHERE, np.array([0.012, 0, 0]), point, np.eye(3).ravel(),
                                np.array(MARK_RGBA, np.float32))
            geom.emission, geom.specular, geom.shininess = 1.0, 0.0, 0.0
            scene.ngeom += 1
        return renderer.render()


def found_at(image: np.ndarray, near: np.ndarray, radius: int = 40) -> np.ndarray:
    """Centroid (column, row) of the magenta pixels within `radius` px of `near`."""
    rows, cols = np.nonzero((image[..., 0] > 200) & (image[..., 1] < 60) & (image[..., 2] > 200))
    close = np.hypot(cols - near[0], rows - near[1]) < radius
    if not close.any():
        raise SystemExit(f"workspace_frame: no marker found near pixel {near.round(1)}")
    return np.array([cols[close].mean(), rows[close].mean()])


def check_axes(scene, view: TopView, data: mujoco.MjData) -> float:
    """Render markers at (+0.1, 0) and (0, +0.1) in the workspace frame; the largest miss (px) from `view.pixel`."""
    centre = np.array(scene.layout.center)
    points = [centre + (0.1, 0.0), centre + (0.0, 0.1)]
    image = render(scene.model, data, view, [np.array([*p, 0.02]) for p in points])
    return max(float(np.linalg.norm(found_at(image, view.pixel(p, 0.02)) - view.pixel(p, 0.02))) for p in points)


def draw(out: Path) -> float:
    """Render and annotate the picture; returns the markers' largest miss in px."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scene = build_scene("lift", "panda", seed=0)
    data = scene.make_data()
    centre, spread = np.array(scene.layout.center), scene.layout.spread
    view = TopView(scene.model, look_at=(centre[0] * 0.55, 0.0), extent=1.1)
    miss = check_axes(scene, view, data)
    if miss > 2.0:
        raise SystemExit(f"workspace_frame: a marker landed {miss:.1f} px from its drawn place: the axes would be wrong")
    image = render(scene.model, data, view, [])

    fig = plt.figure(figsize=(SIZE[1] / 100, SIZE[0] / 100), dpi=100)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.imshow(image)
    ax.set_axis_off()
    box = {"boxstyle": "round,pad=0.25", "fc": "white", "ec": "none", "alpha": 0.85}
    c = view.pixel(centre)
    lo, hi = view.pixel(centre + (spread, spread)), view.pixel(centre - (spread, spread))
    ax.add_patch(plt.Rectangle(lo, hi[0] - lo[0], hi[1] - lo[1], fill=False, ls="--", lw=2, ec="#1f4e9c"))
    ax.text(lo[0], lo[1] - 10, f"lift's cube region: x and y within ±1 spread (±{spread:.3f} m)", color="#1f4e9c",
            fontsize=11, bbox=box)
    arrow = {"arrowstyle": "-|>,head_width=0.6,head_length=1.0", "lw": 4}
    for tip, colour, label, offset in ((centre + (0.1, 0), "#d62728", "+x", (12, 4)),
                                       (centre + (0, 0.1), "#1a9e2a", "+y", (-22, -20))):  # 0.1 m: the markers' places
        t = view.pixel(tip)
        ax.annotate("", xy=t, xytext=c, arrowprops={**arrow, "color": colour})
        ax.text(t[0] + offset[0], t[1] + offset[1], label, color=colour, fontsize=22, weight="bold", bbox=box)
    ax.plot(*c, "o", ms=11, mfc="white", mec="black", mew=2.5)
    ax.text(c[0] + 14, c[1] + 34, f"workspace centre (0, 0)\n= ({centre[0]:.3f}, {centre[1]:.3f}) m in the world",
            color="black", fontsize=11, bbox=box)
    base = view.pixel(np.zeros(2))
    ax.plot(*base, "+", ms=18, mew=3, color="black")
    ax.text(base[0] + 95, base[1] - 6, "robot base: the world origin\n(+x away from it, +y to its left)", color="black",
            fontsize=11, bbox=box)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return miss


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "workspace_frame.png")
    args = parser.parse_args()
    miss = draw(args.out)
    print(f"wrote {args.out} (markers within {miss:.2f} px of the drawn axes)")


if __name__ == "__main__":
    main()
