"""Benchmark: where does the demo's sigma bias come from? (issue 13, a decomposition)

`bench_demo_model_data.py` showed that the demo's Observations refilled from the model give
unbiased pulls, while the photos' own give sigma pulls near -2 (seed 1). The bias therefore
lies between the renderer and the ROI means, or between the renderer's geometry and the
model's. This script renders the demo's photos (`stairfit demo --megapixels 2 --views 9
--seed S`, one process) and keeps, for every photo and face, the renderer's exact noise-free
ROI channel means (`SyntheticPhoto.expected`, with the photo's texture; and
`expected_untextured`, the texture replaced by its mean), which `stairfit simulate`
discards. It then splits each row's residual at the truth (`total`, measured - model) into

* `measurement`: measured - expected - channel_sites (the decoder and the ROI mean, given
  this photo's texture, after the channel-site correction);
* `texture`: expected - expected_untextured (this photo's texture draw over the ROI);
* `geometry`: all-pixel mean - model, where the all-pixel mean is each channel's
  noise-free, untextured radiance averaged over every pixel of the eroded ROI (what the
  channel-site correction estimates, docs/imaging.md §Channel sites) and the model is the
  fit's model of the row (its theta_o, view_spread and aperture; the accurate preset's knobs,
  so that the knobs' own numerical error is not counted);

(the three add up to `total`) and, for the diagnosis of `geometry`:

* `channel_sites`: expected_untextured - all-pixel mean (what the correction removes);
* `geometry_pixels`: the model at the ROI pixels' own mean face coordinate and spread of it,
  minus the model (the table's theta_o is the face centre's);
* `geometry_spread`: the same with the pixels' spread alone;
* `geometry_rest`: all-pixel mean - the model at the pixels' mean and spread;
* `light_rule`: the renderer's light rule (5 nodes) against the fit's, at a point view;
* `interpolation`: the render's profile (PROFILE_NODES, linear between them) against one 8x
  finer, both averaged over the ROI's pixels;
* `geometry_rest_fine`: the finer profile's pixel mean - the model at the pixels' mean and
  spread;
* `setup`: the renderer's value at the face centre against the model at a point view
  (spectra, index, light);
* `conversion`: the model at the pixels' mean and spread, each viewing angle converted to
  radiance at its own angle (4 Gauss nodes, point evaluations), minus the model's own
  aperture average (which weights its nodes with `model.view_conversion`, conventions §9);
* `geometry_rest_conv`: the finer profile's pixel mean - that per-angle conversion.

Each part is projected on the fit's parameters (sigma, scale, floor: the Jacobian of the
model at the truth, every ROI group whitened with the fit's covariance): the shift of the
weighted least-squares estimate that part alone causes, in the fit's standard errors. A
part whose shift in sigma is near the photos' pull is the bias's source. The chi^2 of each
part is split into channel-common and channel-difference terms as in
bench_demo_model_data.py.

With `--fit`, each seed's photos are also fitted as the demo fits them (its preset, the
variant `sharp+floor` forced, `bench_demo_model_data.fit_pulls`) and the pulls are listed with
their mean and sd over the seeds.

Outputs: benchmarks/results/demo_decompose.md and .json (results/quick/ with --quick).

    python benchmarks/bench_demo_decompose.py [--seeds 1 2 3] [--fit]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from bench_demo_calibration import MEGAPIXELS, VIEWS, load_text  # noqa: E402
from bench_demo_model_data import (  # noqa: E402
    chi2_parts,
    demo_options,
    fit_pulls,
    group_covariances,
    truth_params,
)

PARAMS = ("sigma_rad", "scale", "floor")
PARTS = (
    "total",
    "measurement",
    "texture",
    "geometry",
    "channel_sites",
    "geometry_spread",
    "geometry_pixels",
    "geometry_rest",
    "light_rule",
    "interpolation",
    "geometry_rest_fine",
    "setup",
    "conversion",
    "geometry_rest_conv",
)
JAC_PARAMS = ("sigma_rad", "scale", "floor")


def render_recording(seed: int, photos: Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Render the demo's photos of `seed` into `photos` (one process), recording each view's
    renderer expectations: (truth.json, [{face name: (expected, expected_untextured)}] in
    photo order)."""
    from stairfit import simulation as simulate
    from stairfit.imaging import synthetic

    records: list[dict[str, Any]] = []
    original = synthetic.render_photo

    def recording(*args: Any, **kwargs: Any) -> Any:
        photo = original(*args, **kwargs)
        if (
            kwargs.get("texture_seed") is None
            or not records
            or records[-1]["seed"] != kwargs["texture_seed"]
        ):  # a bracket's later exposures share the first's texture: one record per view
            records.append(
                {
                    "seed": kwargs.get("texture_seed"),
                    "inputs": (args[0], args[1], kwargs),
                    "faces": {
                        n: (
                            np.asarray(photo.expected[n]),
                            np.asarray(photo.expected_untextured[n]),
                            all_pixel_means(args[0], args[1][n], args[2][n], kwargs, n),
                        )
                        for n in photo.expected
                    },
                }
            )
        return photo

    views = tuple(float(v) for v in np.linspace(-80.0, 20.0, VIEWS))
    settings = simulate.SimulationSettings(
        megapixels=MEGAPIXELS, views_deg=views, seed=seed, workers=1
    )
    synthetic.render_photo = recording
    try:
        simulate.simulate(photos, settings, progress=False)
    finally:
        synthetic.render_photo = original
    # the same faces' means from a profile 8x finer along the face (the render's linear
    # interpolation between its PROFILE_NODES nodes, measured)
    nodes = simulate.PROFILE_NODES
    simulate.PROFILE_NODES = 8 * (nodes - 1) + 1
    try:
        fine = simulate.face_radiance(settings)
    finally:
        simulate.PROFILE_NODES = nodes
    layout = simulate.SpecimenLayout(settings.wedges_deg)
    names = [simulate._wedge_name(b) for b in layout.wedges_deg]
    for p, rec in enumerate(records):
        size, faces, kwargs = rec["inputs"]
        for k, n in enumerate(names):
            rec["faces"][n] += (all_pixel_means(size, faces[n], fine[p, k], kwargs, n),)
        del rec["inputs"]
    truth = json.loads((photos / simulate.TRUTH_FILE).read_text())
    mid = fine.shape[2] // 2
    return truth, records, fine[:, :, mid, :]


def all_pixel_means(
    size: tuple[int, int], polygon: Any, profile: Any, kwargs: dict[str, Any], name: str
) -> np.ndarray:
    """(3,) each channel's noise-free, untextured radiance averaged over every pixel of the
    eroded ROI (not only that channel's colour sites): the quantity the measurement's
    channel-site correction estimates (docs/imaging.md §Channel sites). The profile is
    interpolated at each pixel's face coordinate as `synthetic._paint_profile` does."""
    from stairfit.imaging import roi_mask

    profile = np.asarray(profile, float)
    if profile.ndim == 1:
        return profile
    w_img, h_img = int(size[0]), int(size[1])
    roi = roi_mask(polygon, (h_img, w_img), kwargs.get("erode_px", 8), photo="x", wedge=name)
    ys, xs = np.nonzero(roi.mask)
    xs, ys = xs + roi.x0, ys + roi.y0
    a, b = (np.asarray(e, float) for e in kwargs["profile_ends"][name])
    d = b - a
    s = np.clip(2.0 * ((xs - a[0]) * d[0] + (ys - a[1]) * d[1]) / float(d @ d) - 1.0, -1, 1)
    nodes = np.linspace(-1.0, 1.0, profile.shape[0])
    means = [np.interp(s, nodes, profile[:, c]).mean() for c in range(3)]
    return np.array([*means, s.mean(), s.var()])


def whitener(groups: list[tuple[np.ndarray, np.ndarray]], n: int) -> Any:
    """x -> the rows of x whitened group by group by each ROI covariance's inverse square root
    (`groups` must be positive definite: `positive_definite`)."""
    factors = []
    for rows, cov in groups:
        w, v = np.linalg.eigh(cov)
        factors.append((rows, (v / np.sqrt(w)) @ v.T))

    def white(x: np.ndarray) -> np.ndarray:
        out = np.zeros_like(x, dtype=float)
        for rows, inv_sqrt in factors:
            out[rows] = inv_sqrt @ x[rows]
        return out

    return white


def decompose(seed: int, work: Path, fit: bool = False) -> dict[str, Any]:
    from stairfit import fitting, pipeline
    from stairfit import simulation as simulate
    from stairfit.presets import PRESETS
    from stairfit.scene import load_scene

    photos = work / f"photos{seed}"
    truth_json, records, centre = render_recording(seed, photos)
    options = demo_options()
    scene = load_scene(photos)
    table = pipeline.measure(scene, work / f"fit{seed}", options)
    obs = pipeline.observations(scene, table).data
    spectral, aperture = pipeline.fit_setup(scene, PRESETS["accurate"])[1:3]
    truth = truth_params(truth_json["parameters"])
    mu = np.asarray(fitting.model_radiance(truth, obs, spectral, aperture=aperture), float)

    names = [simulate._wedge_name(b) for b in truth_json["settings"]["wedges_deg"]]
    if len(records) != len(truth_json["settings"]["views_deg"]):
        raise RuntimeError(f"{len(records)} recorded views, expected one per view")
    p_i, w_i, c_i = (np.asarray(getattr(obs, k)) for k in
                     ("photo_index", "wedge_index", "channel_index"))  # fmt: skip
    expected = np.array(
        [records[p]["faces"][names[w]][0][c] for p, w, c in zip(p_i, w_i, c_i, strict=True)]
    )
    untextured = np.array(
        [records[p]["faces"][names[w]][1][c] for p, w, c in zip(p_i, w_i, c_i, strict=True)]
    )
    ideal = np.array(
        [records[p]["faces"][names[w]][2][c] for p, w, c in zip(p_i, w_i, c_i, strict=True)]
    )
    fine = np.array(
        [records[p]["faces"][names[w]][3][c] for p, w, c in zip(p_i, w_i, c_i, strict=True)]
    )
    s_mean = np.array([records[p]["faces"][names[w]][2][3] for p, w in zip(p_i, w_i, strict=True)])
    s_var = np.array([records[p]["faces"][names[w]][2][4] for p, w in zip(p_i, w_i, strict=True)])
    # the model of each row over its pixels' own viewing angles: theta_o - s h cos(theta_o)
    # at the pixels' mean s, and a uniform spread with the pixels' variance of s
    half_o = 0.5 * scene.camera.angular_extent_deg * np.pi / 180.0
    to = np.asarray(obs.theta_o_rad, float)
    pixel_obs = obs._replace(
        theta_o_rad=to - s_mean * half_o * np.cos(to), view_spread=np.sqrt(3.0 * s_var)
    )
    mu_pixels = np.asarray(
        fitting.model_radiance(truth, pixel_obs, spectral, aperture=aperture), float
    )
    spread_only = obs._replace(view_spread=np.sqrt(3.0 * s_var))
    mu_spread = np.asarray(
        fitting.model_radiance(truth, spread_only, spectral, aperture=aperture), float
    )
    # the renderer's light rule (5 nodes, a point view) against the fit's (accurate preset)
    mu_light = np.asarray(
        fitting.model_radiance(
            truth,
            spread_only._replace(view_spread=np.zeros(obs.n_rows)),
            spectral,
            aperture=aperture._replace(n_nodes=5),
        ),
        float,
    )
    mu_point = np.asarray(
        fitting.model_radiance(
            truth,
            spread_only._replace(view_spread=np.zeros(obs.n_rows)),
            spectral,
            aperture=aperture,
        ),
        float,
    )
    # the same pixels' spread, each viewing angle with its own radiance conversion
    # (1 / cos theta_o at that angle, conventions §9), averaged by a 4-node Gauss rule
    x, gw = np.polynomial.legendre.leggauss(4)
    centre_o = to - s_mean * half_o * np.cos(to)
    mu_conv = np.zeros(obs.n_rows)
    for xk, wk in zip(x, gw, strict=True):
        shifted = obs._replace(
            theta_o_rad=centre_o - xk * np.sqrt(3.0 * s_var) * half_o * np.cos(to),
            view_spread=np.zeros(obs.n_rows),
        )
        mu_conv += (
            0.5
            * wk
            * np.asarray(fitting.model_radiance(truth, shifted, spectral, aperture=aperture), float)
        )
    geometry_info = {
        "s_mean": [float(np.min(s_mean)), float(np.max(s_mean))],
        "spread_ratio_table_over_pixels": [
            float(np.min(np.asarray(obs.view_spread) / np.sqrt(3 * s_var))),
            float(np.max(np.asarray(obs.view_spread) / np.sqrt(3 * s_var))),
        ],
    }
    value = np.asarray(obs.value, float)
    parts = {
        "total": value - mu,
        "measurement": value - expected - (ideal - untextured),
        "texture": expected - untextured,
        "geometry": ideal - mu,
        "channel_sites": untextured - ideal,
        "geometry_spread": mu_spread - mu,
        "geometry_pixels": mu_pixels - mu,
        "geometry_rest": ideal - mu_pixels,
        "light_rule": mu_light - mu_point,
        "interpolation": ideal - fine,
        "setup": np.array([centre[p, w, c] for p, w, c in zip(p_i, w_i, c_i, strict=True)])
        - mu_point,
        "geometry_rest_fine": fine - mu_pixels,
        "conversion": mu_conv - mu_pixels,
        "geometry_rest_conv": fine - mu_conv,
    }

    use = np.asarray(obs.use, bool)
    groups = [(rows, cov) for rows, cov in group_covariances(obs) if use[rows].all()]
    n_groups = len(groups)
    groups = [(rows, cov) for rows, cov in groups if np.linalg.eigvalsh(cov).min() > 0]
    rows_used = np.concatenate([rows for rows, _ in groups])
    white = whitener(groups, obs.n_rows)
    jac = []
    for p in JAC_PARAMS:  # central differences of the model at the truth
        h = {"sigma_rad": 1e-5, "scale": 1e-4 * truth.scale, "floor": 1e-4 * max(truth.floor, 1)}[p]
        up = truth._replace(**{p: getattr(truth, p) + h})
        dn = truth._replace(**{p: getattr(truth, p) - h})
        f_up = np.asarray(fitting.model_radiance(up, obs, spectral, aperture=aperture), float)
        f_dn = np.asarray(fitting.model_radiance(dn, obs, spectral, aperture=aperture), float)
        jac.append((f_up - f_dn) / (2 * h))
    wj = np.stack([white(j) for j in jac], axis=1)[rows_used]
    cov = np.linalg.inv(wj.T @ wj)
    se = np.sqrt(np.diag(cov))
    out: dict[str, Any] = {
        "seed": seed,
        "n_rows": int(rows_used.size),
        "parts": {},
        "geometry": geometry_info,
        "groups_not_positive_definite": n_groups - len(groups),
    }
    if fit:  # the demo's own fit of these photos (its preset; sharp+floor forced)
        fit_spectral, fit_aperture = pipeline.fit_setup(scene, options.preset)[1:3]
        try:
            out["fit"] = fit_pulls(obs, fit_spectral, fit_aperture, options, truth)
        except fitting.FitError as err:  # counted and listed, not hidden
            out["fit_error"] = str(err)
    for name, r in parts.items():
        wr = white(r)[rows_used]
        shift = cov @ (wj.T @ wr)
        by_channel = {
            c: float(np.mean((r / mu)[rows_used][c_i[rows_used] == k])) for k, c in enumerate("RGB")
        }
        out["parts"][name] = {
            "shift_in_se": {p: float(s / e) for p, s, e in zip(JAC_PARAMS, shift, se, strict=True)},
            "chi2": float(wr @ wr),
            "chi2_split": chi2_parts(obs._replace(value=mu + r), mu, groups),
            "mean_relative": by_channel,
        }
    return out


def markdown(result: dict[str, Any]) -> str:
    meta = result["meta"]
    lines = [
        "# Where the demo's sigma bias comes from (issue 13)",
        "",
        f"Seeds {meta['seeds']}; load (1/5/15 min) {meta['load_start']} at the start, "
        f"{meta['load_end']} at the end; wall {meta['wall_s'] / 60:.1f} min. Method: the "
        "script's docstring. Shift: the weighted least-squares change of (sigma, scale, floor) "
        "that the part alone causes, in the fit's standard errors; chi^2 over the used rows "
        "(whitened per ROI), split into channel-common / channel-difference terms.",
        "",
        "| seed | part | sigma shift | scale shift | floor shift | chi^2 (rows) | common / "
        "differences (ROIs) | mean rel. R / G / B (1e-4) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for rec in result["records"]:
        for name in PARTS:
            part = rec["parts"][name]
            s, sp = part["shift_in_se"], part["chi2_split"]
            m = part["mean_relative"]
            lines.append(
                f"| {rec['seed']} | {name} | {s['sigma_rad']:+.2f} | {s['scale']:+.2f} | "
                f"{s['floor']:+.2f} | {part['chi2']:.1f} ({rec['n_rows']}) | "
                f"{sp['common']:.1f} / {sp['differences']:.1f} ({sp['rois']}) | "
                f"{1e4 * m['R']:+.2f} / {1e4 * m['G']:+.2f} / {1e4 * m['B']:+.2f} |"
            )
    lines.append("")
    recs = result["records"]
    lines += [
        f"Mean +- its standard error over the {len(recs)} seeds of each part's shift:",
        "",
        "| part | sigma | scale | floor |",
        "|---|---|---|---|",
    ]
    for name in PARTS:
        cells = []
        for q in JAC_PARAMS:
            x = np.array([r["parts"][name]["shift_in_se"][q] for r in recs])
            se = x.std(ddof=1) / np.sqrt(x.size) if x.size > 1 else float("nan")
            cells.append(f"{x.mean():+.2f} +- {se:.2f}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    fitted = [r for r in recs if "fit" in r]
    if fitted:
        lines += [
            "",
            "The demo's own fit of each seed's photos (its preset, sharp+floor forced): pulls "
            "(value - truth) / stderr and reduced chi^2.",
            "",
            "| seed | sigma | scale | floor | reduced chi^2 | model-error term |",
            "|---|---|---|---|---|---|",
        ]
        for r in fitted:
            f = r["fit"]
            pu = {q: f["params"].get(q, {}).get("pull", float("nan")) for q in PARAMS}
            lines.append(
                f"| {r['seed']} | {pu['sigma_rad']:+.2f} | {pu['scale']:+.2f} | "
                f"{pu['floor']:+.2f} | {f['reduced_chi2']:.2f} | "
                f"{f.get('model_error_frac', 0.0):.2g} |"
            )
        for q in PARAMS:
            x = np.array([r["fit"]["params"][q]["pull"] for r in fitted if q in r["fit"]["params"]])
            if x.size > 1:
                out95 = int(np.sum(np.abs(x) > 1.959964))
                lines.append(
                    f"\n{q}: pull mean {x.mean():+.2f} +- {x.std(ddof=1) / np.sqrt(x.size):.2f}, "
                    f"sd {x.std(ddof=1):.2f}, {out95}/{x.size} outside +-1.96"
                )
    for r in recs:
        if "fit_error" in r:
            lines.append(f"\nSeed {r['seed']}: the fit raised: {r['fit_error']}")
    lines.append("")
    for rec in result["records"]:
        if rec["groups_not_positive_definite"]:
            n_bad = rec["groups_not_positive_definite"]
            lines.append(f"Seed {rec['seed']}: {n_bad} ROI group(s) whose channel covariance "
                         "is not positive definite, left out.")  # fmt: skip
    lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    p.add_argument("--quick", action="store_true", help="seed 1 only")
    p.add_argument("--out-dir", type=Path, default=None)
    p.add_argument("--fit", action="store_true", help="also fit each seed's photos (pulls)")
    args = p.parse_args(argv)
    from stairfit._jaxcache import start_jax

    start_jax()
    seeds = [1] if args.quick else args.seeds
    out_dir = args.out_dir or (HERE / "results" / ("quick" if args.quick else ""))
    out_dir.mkdir(parents=True, exist_ok=True)
    meta: dict[str, Any] = {"load_start": load_text(), "seeds": seeds}
    t0 = time.perf_counter()
    recs = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            rec = decompose(seed, Path(tmp), fit=args.fit)
            recs.append(rec)
            print(json.dumps(rec["parts"], indent=None)[:2000], flush=True)
    meta["wall_s"] = time.perf_counter() - t0
    meta["load_end"] = load_text()
    result = {"meta": meta, "records": recs}
    (out_dir / "demo_decompose.json").write_text(json.dumps(result, indent=1))
    (out_dir / "demo_decompose.md").write_text(markdown(result))
    print(markdown(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
