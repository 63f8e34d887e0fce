"""mjviser's body handles as teleop.web.session_page.body_poses reads them: which handle draws which bodies, and the
poses each handle holds.

mjviser's `ViserMujocoScene.update_from_mjdata` keeps no public list of its handles: they are in
`_mesh_groups` (each a `handle`, its `body_ids`, its `mocap_ids` or None) and the public
`site_handles_by_group` ({(body, group): handle}); whether it draws more than poses (an overlay,
a frame mode) is its private `_any_decor_visible()`. The poses a handle holds are viser's stored
properties (`handle._impl.props.batched_positions`, `.batched_wxyzs`, float32 arrays updated in
place, as viser's own setter does before it queues the message).

Why this is private and what upstream change would retire it: the package's docstring
(teleop/web/viser_internals/__init__.py).
"""

from __future__ import annotations

import numpy as np

PoseEntry = tuple[object, np.ndarray, "np.ndarray | None"]  # (handle, body ids, mocap ids or None)


def pose_entries(scene) -> list[PoseEntry] | None:
    """What a `ViserMujocoScene` draws poses with: (handle, body ids, mocap ids or None) per handle, the bodies'
    poses in the world frame in rows. None where mjviser draws more than poses (an overlay or convex hulls,
    camera tracking, several environments) or is not built as described (another release): then only its own
    update_from_mjdata is right."""
    try:
        if (scene._any_decor_visible() or scene.show_convex_hull  # noqa: SLF001
                or scene.camera_tracking_enabled or scene.num_envs != 1):
            return None
        entries: list[PoseEntry] = [
            (g.handle, np.asarray(g.body_ids), None if g.mocap_ids is None else np.asarray(g.mocap_ids))
            for g in scene._mesh_groups]  # noqa: SLF001
        entries += [(h, np.array([body]), None) for (body, _), h in scene.site_handles_by_group.items()]
    except AttributeError:
        return None
    return entries


def stored_poses(handle) -> tuple[np.ndarray, np.ndarray] | None:
    """The arrays a batched handle holds its poses in (batched_positions (n, 3), batched_wxyzs (n, 4), world frame):
    writing into them in place and then calling scene_stream.send_updates is what viser's setter does. None for a
    handle already removed (a rebuilt scene)."""
    impl = handle._impl  # noqa: SLF001
    if impl.removed:
        return None
    return impl.props.batched_positions, impl.props.batched_wxyzs
