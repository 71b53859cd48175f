"""The plotting helper (mls_mpm/plot.py) and the three plots drawn with it: the loss plot (frames.loss_plot,
byte for byte what it drew before the helper existed), the scaling plot and the tradeoff scatter.

tests/data/loss_plot_few.png and loss_plot_many.png were written by frames.loss_plot before it used plot.py,
for the loss lists below; loss.png of a run must not change when the plotting code is reorganised.
"""
from pathlib import Path

import numpy as np
import pytest

from mls_mpm.frames import loss_plot

DATA = Path(__file__).resolve().parent / "data"
# within two decades (minor 2x and 5x ticks, a dot at every point); a NaN and a zero are left out of the curve
FEW = [3.2e-2, 2.1e-2, 1.5e-2, float("nan"), 9.7e-3, 7.0e-3, 0.0, 5.6e-3, 4.9e-3, 4.6e-3]
# 137 points over five decades (decade ticks only, one dot at the end), another size and title
MANY = list(2.0 * np.exp(-np.arange(137) / 12.0))


@pytest.mark.parametrize("name, losses, kwargs", [
    ("loss_plot_few.png", FEW, {}),
    ("loss_plot_many.png", MANY, {"size": (320, 200), "title": "round 2"}),
])
def test_loss_plot_bytes_unchanged(tmp_path, name, losses, kwargs):
    path = loss_plot(losses, tmp_path / name, **kwargs)
    assert path.read_bytes() == (DATA / name).read_bytes()
