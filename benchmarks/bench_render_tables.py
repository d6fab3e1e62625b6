"""The RGL tables of `stairfit render` (app/render/_rgl.py): their error against the model and
their cost, per resolution (docs/render.md "Resolution").

Error: Mitsuba's `measured` plugin reading a table against `stairfit.render.mitsuba_value` (the
model), relative, per pair (luminance-free: the G channel), at two sets of direction pairs:
the lab's (each face's camera and lamp directions in every photo of a physically based set's
truth.json, and three copies jittered by about 1.5 deg) and pairs near the lobes (cameras
uniform below 80 deg elevation, lights drawn from `stairfit.render.Mixture`; the summed error
over the summed value). Cost: CPU and wall seconds to tabulate (the machine's load average is
printed beside them: other processes slow the wall time, not the CPU time).

    python benchmarks/bench_render_tables.py --truth ~/.cache/stairfit/pbr/dev/truth.json
    python benchmarks/bench_render_tables.py --qualities draft default fine --wedges 30 60

Writes one block of results (Markdown) to stdout; benchmarks/results/render_tables.md keeps
them, newest first.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from stairfit import render
from stairfit.render import _rgl

RESOLUTIONS = {
    **render.QUALITIES,
    "12x25x48": render.Resolution(theta_i=12, phi_i=25, samples=48),
}


def base_to_face(v: np.ndarray, beta2_deg: float) -> np.ndarray:
    b = math.radians(beta2_deg)
    return np.array([v[0] * math.cos(b) + v[2] * math.sin(b), v[1],
                     -v[0] * math.sin(b) + v[2] * math.cos(b)])  # fmt: skip


def lab_pairs(truth: dict, beta2_deg: float, rng: np.random.Generator) -> tuple:
    """(cameras, lights) in the table's local frame for every photo's face of that wedge."""
    name = f"w{beta2_deg:g}"
    cams, lights = [], []
    for photo in truth["photos"]:
        face = photo["faces"].get(name)
        if not face:
            continue
        v0 = base_to_face(face["view_dir"], beta2_deg)
        l0 = base_to_face(face["light_dir"], beta2_deg)
        for j in range(4):
            v = v0 + (rng.normal(size=3) * 0.015 if j else 0.0)
            lt = l0 + (rng.normal(size=3) * 0.015 if j else 0.0)
            cams.append(_rgl.to_local(v / np.linalg.norm(v)))
            lights.append(_rgl.to_local(lt / np.linalg.norm(lt)))
    return np.array(cams), np.array(lights)


def lobe_pairs(material: render.Material, beta2_deg: float, n: int,
               rng: np.random.Generator) -> tuple:  # fmt: skip
    v = rng.normal(size=(4 * n, 3))
    v[:, 2] = np.abs(v[:, 2])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    cams = v[v[:, 2] > math.cos(math.radians(80.0))][:n]
    light, _ = render.Mixture(material, beta2_deg, _rgl.to_face(cams), "light").sample(
        rng.random(len(cams)), rng.random((len(cams), 2)))  # fmt: skip
    ok = light[:, 2] > 0.02
    return cams[ok], _rgl.to_local(light[ok])


def measured(path: Path, cams: np.ndarray, lights: np.ndarray) -> np.ndarray:
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    bsdf = mi.load_dict({"type": "measured", "filename": str(path)})
    ctx = mi.BSDFContext()
    out = []
    for c, lt in zip(cams, lights, strict=True):
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*c)
        si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
        out.append(np.array(bsdf.eval(ctx, si, mi.Vector3f(*lt)))[1])
    return np.array(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--truth", type=Path, default=None,
                        help="a physically based set's truth.json (tests/pbr_photos.py)")
    parser.add_argument("--qualities", nargs="+", default=["draft", "12x25x48", "default"],
                        choices=sorted(RESOLUTIONS))
    parser.add_argument("--wedges", nargs="+", type=float, default=[30.0, 60.0])
    parser.add_argument("--edge-radius-um", type=float, default=26.9)
    args = parser.parse_args(argv)
    truth = json.loads(args.truth.read_text()) if args.truth else None
    material = render.Material("ggx", ((0.0, math.atan(0.0636)),), args.edge_radius_um, 150.0,
                               (1.46,) * 3, 0.021)  # fmt: skip
    print(f"## {time.strftime('%Y-%m-%d')}: GGX alpha 0.0636, r {args.edge_radius_um:g} um, "
          f"n 1.46, body 0.021; lab pairs from {args.truth or 'none'}\n")
    print("| tables | wedge | lab pairs: median / p90 / max | lobe pairs: summed | "
          "CPU s | wall s | load |")
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.qualities:
            res = RESOLUTIONS[name]
            for beta2 in args.wedges:
                rng = np.random.default_rng(int(beta2))
                path = Path(tmp) / f"{name}_{beta2:g}.bsdf"
                t0, c0 = time.perf_counter(), time.process_time()
                render.write_bsdf(path, material, beta2, res)
                wall, cpu = time.perf_counter() - t0, time.process_time() - c0
                lab = "-"
                if truth is not None:
                    cams, lights = lab_pairs(truth, beta2, rng)
                    want = render.mitsuba_value(material, beta2, cams, lights,
                                                render.arc_grid(material, beta2, res.arcs))[:, 1]
                    rel = np.abs(measured(path, cams, lights) - want) / want
                    lab = (f"{np.median(rel):.1%} / {np.percentile(rel, 90):.1%} / "
                           f"{rel.max():.1%} ({len(rel)})")  # fmt: skip
                cams, lights = lobe_pairs(material._replace(edge_radius_um=0.0), beta2, 2000, rng)
                want = render.mitsuba_value(material, beta2, cams, lights,
                                            render.arc_grid(material, beta2, res.arcs))[:, 1]
                summed = np.abs(measured(path, cams, lights) - want).sum() / want.sum()
                label = f"{name} ({res.theta_i} x {res.phi_i} x {res.samples}^2)"
                print(f"| {label} | {beta2:g} | {lab} | {summed:.1%} | {cpu:.1f} | {wall:.1f} "
                      f"| {os.getloadavg()[0]:.1f} |", flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
