"""The report's figures are cropped to the box savefig's bbox_inches="tight" finds, measured without the second draw
"tight" costs (reporting.figures._tight_bbox): nothing of the figure is cut off, and no more than a few points of
margin are added."""

from __future__ import annotations

import io
import re

import numpy as np
import pytest

from symfunnel.reporting import figures as F


def _view(fig, bbox) -> tuple[float, float]:
    buf = io.StringIO()
    fig.savefig(buf, format="svg", bbox_inches=bbox)
    w, h = re.search(r'viewBox="0 0 ([0-9.]+) ([0-9.]+)"', buf.getvalue()).groups()
    return float(w), float(h)


@pytest.mark.parametrize("joints", [1, 2, 7])
def test_the_crop_holds_what_tight_holds_with_at_most_a_few_points_more(joints):
    plt = F._plt()
    with plt.rc_context(F._RC):
        fig, axes = F._joint_axes(joints, "A title wider than most: q_i(t) against the reference q_d,i(t)")
        t = np.linspace(0, 20, 500)
        for j, ax in enumerate(axes):
            ax.plot(t, 1e4 * np.sin(t + j), label="a long legend label, outside the axes")
            ax.set_ylabel(f"joint {j + 1} [N m]")
        F._legend_outside(axes[0])
        axes[-1].set_xlabel("t [s]")
        tight = _view(fig, "tight")
        ours = _view(fig, F._tight_bbox(fig))
    plt.close(fig)
    for a, b in zip(ours, tight):
        assert b - 0.5 <= a <= b + 8.0, (ours, tight)      # points: never smaller, at most ~0.1 in larger


def test_a_figure_with_a_layout_engine_keeps_tight():
    plt = F._plt()
    fig, _ = plt.subplots(1, 2, constrained_layout=True)
    assert F._tight_bbox(fig) == "tight"
    plt.close(fig)
