"""Quality presets: named settings of every knob that trades accuracy for time.

The knobs are in the README's "Speed and accuracy" section, their measured effect in
docs/performance.md; the numbers come from `python benchmarks/bench_tradeoff.py`, which
measures every knob setting (model error against a converged reference, fit bias in standard
errors on synthetic data with known truth, wall time with compilation apart) and then each
preset as a whole, writing
`benchmarks/results/tradeoff.{csv,md}` and the Pareto plot `tradeoff_pareto.png`. The three
presets are points on that measured front (case: dispersive PLA, a 5-deg light seen over a 3-deg
face, sigma 6 deg, 2% noise):

* aperture nodes: 1 node ignores a finite light (3% model error, 6x the noise; fitted
  parameters biased by up to 23 standard errors); 2 nodes cut it to 0.29% (0.23 x noise,
  bias 0.16 stderr) for 1.5x the fit time, so every preset uses at least 2 (scenes without
  an angular size always use 1: nothing to integrate);
* spectral sampling: one effective wavelength leaves 0.28% (0.22 x noise) of dispersion error;
  5 nm sampling removes it for 2-3x the fit time and 6x the posterior time (accurate only);
* starts: on the standard scene 1 to 4 starts find the same optimum; the extra starts guard
  against the local minima of broad, overlapping lobes (docs/fitting.md §3);
* posterior: the stopping rule (longer than tau_factor autocorrelation times, tau settled) is
  checked every `posterior_chunk_steps`; every 100 steps, tau_factor 10 and 20 both stop at
  700-800 steps (Monte Carlo error of a mean 0.04 sd); every 500 steps, tau_factor 20 and 50
  ran 2500 steps (0.022 sd) for 3x the time; 100 tau takes 4000 steps (0.018 sd);
* float32 figures: half the time of float64 at full sampling, error unchanged at 3e-3;
* diffuse nodes 3 / 6 / 8: error 1e-4 / 3e-9 / 3e-12 of the maximum;
* rounded resolution 2 / 4 / 8: error 1e-4 / 2e-5 / 2e-6.
* fillet rays 256 / 512 / 4096 (the filleted rungs only): rms error 0.55 / 0.25 / below 0.1
  measurement standard errors on the standard scene at 1% noise and sigma 2 deg, the worst
  of five radius pairs, against 16384 rays (measured by `benchmarks/bench_rounded.py
  --fillet-accuracy`, not by bench_tradeoff; docs/rounded.md §11); 512 rays on the fillet's
  footprint are as accurate as 2048 spread uniformly over the period.

What each preset costs (a least-squares fit and a posterior of the standard scene) and its fit
bias are in docs/performance.md and benchmarks/results/tradeoff.md. `fit` uses `balanced` by
default. The `ladder` field (model choice, not numerical
accuracy) is not measured by the benchmark.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from .errors import UserError


@dataclass(frozen=True)
class Preset:
    """Every accuracy/speed knob of a fit.

    * `spectral`: "effective" (one effective wavelength per camera channel) or "full" (5 nm
      sampling, 81 wavelengths per channel) [conventions §8].
    * `aperture_nodes`: Gauss-Legendre nodes per axis over the angular size of the light and of
      the viewed face (1 = point light, point view) [conventions §9].
    * `rounded_resolution`: quadrature resolution of the rounded-edge model (docs/rounded.md).
    * `fillet_rays`: rays per period of the fillet correction's tracer (docs/rounded.md §11;
      the filleted rungs only). Its error falls like `1 / rays` and is smoothed by the
      broadening; the accuracy check after a fit compares with `accurate`'s count.
    * `diffuse_nodes`: nodes per piece of the broadened diffuse integral (figures).
    * `sigma_starts_deg`: multi-start widths of the least-squares fit.
    * `ladder`: "shared" (one sigma; 8 variants) or "full" (also one sigma per wedge; 16).
    * `rounded_rungs`: "always" fits the rounded-edge variants of the ladder; "when_needed"
      fits them only when the best sharp variant does not describe the data (it needs a
      model-error term, or its chi^2 tail probability is below 1e-3; `stairfit.fitting.
      rounding_needed`). A rounded fit compiles several times longer than a sharp one.
    * `posterior_tau_factor`: the chain must be this many autocorrelation times long;
      `posterior_max_steps`: the step limit (then a warning); `posterior_chunk_steps`: how
      often (in steps) the stopping rule is checked (a chain stops at a multiple of it).
    * `float32_figures`: evaluate figures in float32 (fits are always float64).
    * `ladder_budget_gflop`: no further variant of the ladder is started once its fits have
      done this much work (solver steps weighted by XLA's flop count of one step,
      `stairfit.fitting.step_gflop`; after the lab model's kernel probes; the summary lists
      those not tried). Work, not time, so that the same photos give the same choice on any
      machine, busy or not; None: every variant is fitted.
    """

    name: str
    spectral: str
    aperture_nodes: int
    rounded_resolution: int
    fillet_rays: int
    diffuse_nodes: int
    sigma_starts_deg: tuple[float, ...]
    ladder: str
    rounded_rungs: str
    posterior_tau_factor: float
    posterior_max_steps: int
    posterior_chunk_steps: int
    float32_figures: bool
    ladder_budget_gflop: float | None = None

    def as_dict(self) -> dict[str, object]:
        """For results.json."""
        return asdict(self)


BALANCED_GFLOP = 400.0
"""The balanced preset's ladder budget (Gflop of solver work after the kernel probes): enough
for the whole ladder of the physically based dev set and of the in-plane standard scene, and
an end to a misfitting climb into costly rungs (the measured work of each:
benchmarks/results/lab_fit.md)."""

FAST_GFLOP = 200.0
"""The fast preset's ladder budget: half the balanced one."""

PRESETS: dict[str, Preset] = {
    "fast": Preset(
        name="fast",
        spectral="effective",
        aperture_nodes=2,
        rounded_resolution=2,
        fillet_rays=256,
        diffuse_nodes=3,
        sigma_starts_deg=(2.0, 8.0),
        ladder="shared",
        rounded_rungs="when_needed",
        posterior_tau_factor=10.0,
        posterior_max_steps=1_500,
        posterior_chunk_steps=100,
        float32_figures=True,
        ladder_budget_gflop=FAST_GFLOP,
    ),
    "balanced": Preset(
        name="balanced",
        spectral="effective",
        aperture_nodes=2,
        rounded_resolution=4,
        fillet_rays=512,
        diffuse_nodes=6,
        sigma_starts_deg=(1.0, 4.0, 12.0),
        ladder="shared",
        rounded_rungs="when_needed",
        posterior_tau_factor=20.0,
        posterior_max_steps=20_000,
        posterior_chunk_steps=100,
        float32_figures=False,
        ladder_budget_gflop=BALANCED_GFLOP,
    ),
    "accurate": Preset(
        name="accurate",
        spectral="full",
        aperture_nodes=4,  # even: a light interval split at a kink gets 2 + 2 (docs/fitting.md §3)
        rounded_resolution=8,
        fillet_rays=4096,
        diffuse_nodes=8,
        sigma_starts_deg=(1.0, 3.0, 10.0, 30.0),
        ladder="full",
        rounded_rungs="always",
        posterior_tau_factor=100.0,
        posterior_max_steps=50_000,
        posterior_chunk_steps=500,
        float32_figures=False,
    ),
}


def get_preset(name: str) -> Preset:
    """A preset by name; a clear error lists the others."""
    try:
        return PRESETS[name]
    except KeyError:
        raise UserError(
            f"--preset: unknown preset {name!r}; use one of {', '.join(PRESETS)}"
        ) from None
