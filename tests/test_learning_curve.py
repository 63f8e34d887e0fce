"""bench/learning_curve.py's picture: success against demos and sources, drawn from the runs' JSON.

The runs themselves (about an hour of training) are the bench's; here the plot is drawn from reports of
the shape bench/train_eval.sh prints, and read back as an image.
"""

from __future__ import annotations

import numpy as np
from PIL import Image

from bench.learning_curve import RUNS, plot


def _report(demos: int, sources: int, rate: float) -> dict:
    return {"task": "lift", "demos": demos, "sources": sources, "steps": 10000, "success_rate": rate,
            "ci95": [max(0.0, rate - 0.1), min(1.0, rate + 0.1)]}


def test_the_plot_draws_every_run(tmp_path):
    rates = {(10, 3): 0.1, (50, 3): 0.5, (200, 3): 0.9, (200, 1): 0.3}
    assert set(rates) == set(RUNS)
    path = tmp_path / "curve.png"
    plot([_report(d, s, rates[d, s]) for d, s in RUNS], path)
    image = np.asarray(Image.open(path).convert("RGB")).astype(int)
    assert image.shape[0] > 300 and image.shape[1] > 800
    # the curve's line and the bars are drawn in colour: the left panel holds the blue line, the right its two bars
    blue = (image[..., 2] - image[..., 0] > 60) & (image[..., 2] > 120)
    width = image.shape[1]
    assert blue[:, : width * 2 // 3].sum() > 200 and blue[:, width * 2 // 3 :].sum() > 2000
    # a higher rate makes a taller bar: the 3-source bar (right) rises above the 1-source one (left)
    right = blue[:, width * 2 // 3 :]
    columns = np.flatnonzero(right.sum(axis=0) > 20)
    gap = int(np.argmax(np.diff(columns)))  # the space between the two bars
    bars = [columns[: gap + 1], columns[gap + 1 :]]
    assert all(len(bar) > 10 for bar in bars)
    tops = [np.flatnonzero(right[:, int(np.median(bar))])[0] for bar in bars]
    assert tops[1] < tops[0]
