"""Benchmark: what one call of the log posterior costs the sampler, and a whole posterior, with
the arrays handed to the compiled program as NumPy arrays (now) against converted by
`jnp.asarray` on every call (before 6 December 2026), side by side in the same process.

emcee calls `Target.log_prob` thousands of times per posterior (each differential-evolution
step evaluates half the ensemble), so the Python around the compiled program is a large part of
a posterior's time on small scenes. The baseline is the earlier `log_prob`, reproduced here
(the only difference: `jnp.asarray` of the walkers, the optimum and the free slots per call).

* per call: median of 2000 calls of each, interleaved in rounds, on the walkers of a real run;
* whole posterior: `sample_posterior` of the same least-squares fit (warm: the program is
  compiled before timing), `--repeats` interleaved rounds, medians (range); the values of both
  are checked to be identical.

Scenes: the calibration tests' small scene (2 wedges x 9 views, one channel, 18 rows; chains of
20 tau as tests/fitting/test_posterior.py's short calibration) and the standard scene (6 wedges
x 19 views x 3 channels, 342 rows; the default stopping rule).

    python benchmarks/bench_posterior_calls.py [--repeats 5] [--out FILE]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
import warnings
from collections.abc import Callable
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # zoo: the tests' scenes

from stairfit._jaxcache import fast_compile  # noqa: E402

fast_compile()  # as the command line compiles (app/_jaxcache.py)

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import zoo  # noqa: E402

from stairfit import fitting  # noqa: E402
from stairfit.fitting import _export, _posterior  # noqa: E402
from stairfit.fitting.posterior import sample_posterior  # noqa: E402

DEG = np.pi / 180
TRUTH = fitting.Params(sigma_rad=8 * DEG, delta_n=0.02, scale=1.0, floor=0.003)


def baseline_log_prob(self: _posterior.Target, theta: np.ndarray) -> np.ndarray:
    """`Target.log_prob` as it was before: the three arrays converted by `jnp.asarray`."""
    n = theta.shape[0]
    if n < self.batch:
        theta = np.concatenate([theta, np.repeat(theta[:1], self.batch - n, axis=0)])
    slots, dists = _posterior.split_priors(self.priors)
    out = _export.call(
        "log_probability",
        lambda th, p, d, z, s: _posterior._batched_log_probability(
            th, self.static, slots, p, d, z, s
        ),
        _posterior._program_key(self.static, slots),
        (jnp.asarray(theta), dists, self.data, jnp.asarray(self.base_z), jnp.asarray(self.slots)),
        lambda leaves: leaves[0],
    )
    return np.array(out)[:n]


CURRENT = _posterior.Target.log_prob


def _scenes() -> dict[str, tuple[Any, dict[str, Any]]]:
    """name -> (least-squares fit, sample_posterior keywords)."""
    small = zoo.small(TRUTH, 700)
    variant = fitting.variant("dn_floor", "delta_n", "floor")
    fit_small = fitting.fit_least_squares(small.obs, small.spec, variant, emit_warnings=False)
    short = {"tau_factor": 20.0, "chunk_steps": 250, "rhat_max": np.inf, "ess_min": 0.0}
    std = zoo.standard(fitting.Params(sigma_rad=6 * DEG), 1)
    fit_std = fitting.fit_least_squares(std.obs, std.spec, emit_warnings=False)
    return {
        "small scene (18 rows, 20 tau)": (fit_small, short),
        "standard scene (342 rows, default rule)": (fit_std, {}),
    }


def _with_log_prob(fn: Callable[..., np.ndarray], run: Callable[[], Any]) -> Any:
    _posterior.Target.log_prob = fn
    try:
        return run()
    finally:
        _posterior.Target.log_prob = CURRENT


def _posterior_run(fit: Any, kw: dict[str, Any]) -> Any:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return sample_posterior(fit, seed=1, emit_warnings=False, **kw)


def _walkers(fit: Any, kw: dict[str, Any]) -> tuple[_posterior.Target, np.ndarray]:
    """The target and the sampler's first batch of walkers (the whole ensemble; smaller
    batches are padded to it, `Target.batch`)."""
    seen: dict[str, Any] = {}

    def spy(self: _posterior.Target, theta: np.ndarray) -> np.ndarray:
        seen.setdefault("call", (self, np.array(theta)))
        return CURRENT(self, theta)

    _with_log_prob(spy, lambda: _posterior_run(fit, {**kw, "chunk_steps": 10, "max_steps": 10}))
    return seen["call"]


def _per_call_us(target: _posterior.Target, theta: np.ndarray, rounds: int = 4) -> dict[str, float]:
    times: dict[str, list[float]] = {"now": [], "before": []}
    fns = {"now": CURRENT, "before": baseline_log_prob}
    for fn in fns.values():
        for _ in range(50):
            fn(target, theta)
    for _ in range(rounds):
        for name, fn in fns.items():
            for _ in range(500):
                t0 = time.perf_counter()
                fn(target, theta)
                times[name].append(time.perf_counter() - t0)
    return {k: 1e6 * statistics.median(v) for k, v in times.items()}


def _fmt(ts: list[float]) -> str:
    return f"{statistics.median(ts):.2f} s ({min(ts):.2f}-{max(ts):.2f})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5, help="interleaved rounds of posteriors")
    ap.add_argument("--out", type=Path, help="also write the table (markdown) to this file")
    args = ap.parse_args()

    lines = [
        f"bench_posterior_calls.py, {datetime.now():%Y-%m-%d %H:%M}, jax {jax.__version__}, "
        f"{args.repeats} rounds",
        "",
        "| scene | walkers per call | one call now | one call before | posterior now "
        "| posterior before | same values |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, (fit, kw) in _scenes().items():
        target, theta = _walkers(fit, kw)
        same_call = np.array_equal(CURRENT(target, theta), baseline_log_prob(target, theta))
        per_call = _per_call_us(target, theta)
        runs: dict[str, list[float]] = {"now": [], "before": []}
        medians: dict[str, np.ndarray] = {}
        for _ in range(args.repeats):
            for label, fn in (("now", CURRENT), ("before", baseline_log_prob)):
                t0 = time.perf_counter()
                post = _with_log_prob(fn, lambda fit=fit, kw=kw: _posterior_run(fit, kw))
                runs[label].append(time.perf_counter() - t0)
                medians[label] = np.asarray(post.median)
        same = same_call and np.array_equal(medians["now"], medians["before"])
        lines.append(
            f"| {name} | {theta.shape[0]} | {per_call['now']:.0f} us | "
            f"{per_call['before']:.0f} us | {_fmt(runs['now'])} | {_fmt(runs['before'])} | "
            f"{'yes' if same else 'NO'} |"
        )
        print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out is not None:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
