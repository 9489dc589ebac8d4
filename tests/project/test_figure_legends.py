"""Figures that explain themselves: the corner plot's legend and no stray log warning from corner."""

from __future__ import annotations

import logging

import numpy as np

from brdfjax.sample import _outputs


def test_corner_plot_has_a_legend_and_no_stray_contour_warning(tmp_path, caplog, monkeypatch):
    seen = {}
    real_save = _outputs.save_figure_atomic

    def save(fig, path, *args, **kwargs):
        seen["legend"] = [t.get_text() for lg in fig.legends for t in lg.get_texts()]
        return real_save(fig, path, *args, **kwargs)

    monkeypatch.setattr(_outputs, "save_figure_atomic", save)
    x = np.random.default_rng(1).standard_normal((12, 3))  # too few samples for corner's contours
    with caplog.at_level(logging.WARNING):
        path = _outputs.plot_corner(tmp_path / "corner.png", x, ["a", "b", "c"], ["1", "1", "deg"], truths=[0, 0, 0])
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not [r for r in caplog.records if "contours" in r.getMessage()]
    assert any(t.startswith("red: least-squares fit") for t in seen["legend"]), seen
    assert any("16, 50, 84 % posterior quantiles" in t for t in seen["legend"])
    assert any("without contours" in t for t in seen["legend"])
    assert not logging.getLogger().filters  # the filter is removed after the call
