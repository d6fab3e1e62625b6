"""The report's figures drawn by a second process (app/_drawing.py, issue 14): the same PNG
bytes as drawing them here, the process never imports JAX, and every failure (a figure that
does not pickle, a process that died, an error in the block) still leaves every figure
written, drawn here, and nothing written after the block."""

from __future__ import annotations

import os
import signal
import sys
from types import SimpleNamespace

import numpy as np
import pytest
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter

from stairfit import _drawing, figures

DEG = np.pi / 180


def _fit_outcome() -> SimpleNamespace:
    """What `report.fit_per_wedge` reads: two wedges x three channels, error bars, log axes."""
    theta = np.linspace(-60.0, 60.0, 13)
    rows = [(w, c, k) for w in (0, 1) for c in range(3) for k in range(theta.size)]
    value = np.array([(1e3 * np.exp(-((theta[k] / 30) ** 2)) + 50.0) * (1 + 0.3 * w + 0.01 * c)
                      for w, c, k in rows])  # fmt: skip
    obs = SimpleNamespace(
        wedge_index=np.array([w for w, _, _ in rows]),
        channel_index=np.array([c for _, c, _ in rows]),
        value=value,
        use=np.array([k != 3 for _, _, k in rows]),
    )
    wedges = tuple(SimpleNamespace(name=f"w{a}", angle_deg=float(a)) for a in (10, 45))
    fit = SimpleNamespace(model=value, uncertainty=0.02 * value)
    return SimpleNamespace(
        selection=SimpleNamespace(fit=fit, chosen="sharp"),
        observations=obs,
        scene=SimpleNamespace(specimen=SimpleNamespace(wedges=wedges)),
        row_info=[{"theta_o_deg": theta[k]} for _, _, k in rows],
    )


def _report_like_figures() -> list[tuple[str, Figure]]:
    """Figures made the way the report makes them: one from model values computed by JAX
    (`brdf_map`, an image with a colour bar) and one from fit data (`fit_per_wedge`)."""
    from stairfit.report import fit_per_wedge

    return [
        ("map.png", figures.brdf_map([10, 45], n=1.46, sigma_deg=5.0, step_deg=5.0)),
        ("fit.png", fit_per_wedge(_fit_outcome())),
    ]


def test_figures_drawn_by_the_process_are_the_bytes_drawn_here(tmp_path):
    here, there = tmp_path / "here", tmp_path / "there"
    for name, fig in _report_like_figures():
        figures.save(fig, here / name)
    with _drawing.drawing() as draw:
        assert draw.in_process
        for name, fig in _report_like_figures():
            assert draw(fig, there / name) == there / name
    for name in ("map.png", "fit.png"):
        assert (there / name).read_bytes() == (here / name).read_bytes(), name


def _modules_loaded() -> tuple[bool, bool, int]:
    """In the drawing process: (jax imported, matplotlib imported, its process id)."""
    return "jax" in sys.modules, "matplotlib" in sys.modules, os.getpid()


def test_the_drawing_process_draws_without_jax(tmp_path):
    with _drawing.drawing() as draw:
        for name, fig in _report_like_figures():
            draw(fig, tmp_path / name)
        draw.finish()
        jax_there, mpl_there, pid = draw._pool.submit(_modules_loaded).result()
    assert pid != os.getpid()  # really another process
    assert mpl_there and not jax_there  # unpickling the figures needed matplotlib only
    assert "jax" in sys.modules  # (here it is: brdf_map evaluated the model)


def test_a_figure_that_does_not_pickle_is_drawn_here(tmp_path):
    fig = Figure(figsize=(2, 2))
    ax = fig.subplots()
    ax.plot([0, 1], [0, 1])
    ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:.1f}"))  # a lambda: no pickle
    with _drawing.drawing() as draw:
        draw(fig, tmp_path / "lambda.png")
        assert (tmp_path / "lambda.png").stat().st_size > 0  # written at once, here


def test_figures_of_a_process_that_died_are_drawn_here(tmp_path):
    names = []
    with _drawing.drawing() as draw:
        pid = draw._pool.submit(_modules_loaded).result()[2]
        os.kill(pid, signal.SIGKILL)
        for name, fig in _report_like_figures():
            draw(fig, tmp_path / name)
            names.append(name)
    for name in names:
        assert (tmp_path / name).stat().st_size > 0, name
    reference = tmp_path / "reference.png"
    figures.save(_report_like_figures()[1][1], reference)
    assert (tmp_path / "fit.png").read_bytes() == reference.read_bytes()


def test_an_error_in_the_block_stops_the_process_after_the_figures_it_was_given(tmp_path):
    with pytest.raises(RuntimeError, match="stop"), _drawing.drawing() as draw:
        for name, fig in _report_like_figures():
            draw(fig, tmp_path / name)
        pool = draw._pool
        raise RuntimeError("stop")
    # the process has stopped: nothing it was still doing can write into the folder later
    with pytest.raises(RuntimeError):
        pool.submit(_modules_loaded)
    written = {p.name for p in tmp_path.iterdir()}
    assert written <= {"map.png", "fit.png"}
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())  # no partial files


def test_without_the_process_figures_are_drawn_here(tmp_path):
    with _drawing.drawing(in_process=False) as draw:
        assert not draw.in_process
        fig = _report_like_figures()[1][1]
        draw(fig, tmp_path / "fit.png")
        assert (tmp_path / "fit.png").stat().st_size > 0


def test_a_fit_draws_in_the_process_only_beside_a_posterior(monkeypatch, tmp_path):
    # without a posterior there is nothing to draw beside; a study's workers draw their own
    from stairfit.commands import fit

    seen = []
    monkeypatch.setattr(fit, "measure", lambda scene, out, options: None)
    monkeypatch.setattr(fit, "prefetch", lambda *args: None)
    monkeypatch.setattr(fit, "_fit_measured", lambda *args: seen.append(args[-1].in_process))
    cases = [(True, True), (False, True), (True, False)]
    for posterior, figure_process in cases:
        options = SimpleNamespace(
            posterior=posterior, figure_process=figure_process, freeze_imports=False
        )
        fit.fit_scene(SimpleNamespace(), tmp_path, options)
    assert seen == [True, False, False]


class _NoProcesses:
    """A `ProcessPoolExecutor` of a machine that allows none: fails at creation, or (`late`)
    when its process is spawned at the first submit."""

    late = False

    def __init__(self, *args, **kwargs):
        if not self.late:
            raise OSError("no semaphores here")
        self.stopped = False

    def submit(self, *args):
        raise OSError("cannot spawn")

    def shutdown(self, wait=True, cancel_futures=False):
        self.stopped = True


@pytest.mark.parametrize("late", [False, True])
def test_where_no_process_can_start_figures_are_drawn_here(monkeypatch, tmp_path, late):
    monkeypatch.setattr(_NoProcesses, "late", late)
    monkeypatch.setattr(_drawing, "ProcessPoolExecutor", _NoProcesses)
    with _drawing.drawing() as draw:
        assert not draw.in_process
        draw(_report_like_figures()[1][1], tmp_path / "fit.png")
        assert (tmp_path / "fit.png").stat().st_size > 0
