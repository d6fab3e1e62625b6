"""imaging/_stripes.py: the layer stripes of one ROI (docs/imaging.md §Layer stripes)."""

from __future__ import annotations

import numpy as np

from stairfit.imaging._stripes import MIN_PERIOD_PX, MIN_PERIODS, Pixels, fit_stripes


def test_a_roi_too_narrow_across_the_layers_for_any_stripes_has_none() -> None:
    """A face 3 px across its layer lines (a grazing view) cannot hold MIN_PERIODS periods of
    even the shortest period: no stripes, where the search over frequencies was empty and
    failed before (the variant set's 50-deg face seen at 80 deg)."""
    assert MIN_PERIODS * MIN_PERIOD_PX > 3.0
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:3, 0:400]
    x, y = x.ravel().astype(float), y.ravel().astype(float)
    colour = np.where((x % 2 == 0) & (y % 2 == 0), 0, np.where((x % 2 == 1) & (y % 2 == 1), 2, 1))
    value = 1000.0 + 10.0 * np.sin(2 * np.pi * y / 1.5) + rng.normal(0.0, 5.0, x.size)
    px = Pixels(x, y, colour, value, np.ones(x.size, bool))
    assert fit_stripes(px, across=np.array([0.0, 1.0])) is None
