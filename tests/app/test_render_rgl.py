"""The RGL measured-material file (`.bsdf`, app/render/_rgl.py): Mitsuba's tensor-file layout,
and Mitsuba's own `measured` plugin reading it back: exactly the model at the tables' nodes,
and between them an error that shrinks as the tables grow (docs/render.md "Resolution")."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from stairfit import render
from stairfit.render import _rgl


def test_tensor_file_round_trip(tmp_path: Path) -> None:
    """Fields of every kind come back with their names, dtypes, shapes and values, each at an
    8-byte aligned offset (the layout of Mitsuba's src/core/tensor.cpp)."""
    rng = np.random.default_rng(0)
    fields = {
        "description": "a staircase",
        "jacobian": np.array([1], np.uint8),
        "theta_i": rng.random(5).astype(np.float32),
        "vndf": rng.random((2, 3, 4, 5)).astype(np.float32),
        "rgb": rng.random((2, 3, 3, 7, 7)).astype(np.float32),
        "index": np.arange(6, dtype=np.int64).reshape(2, 3),
    }
    data = render.tensor_bytes(fields)
    assert data[:12] == b"tensor_file\0" and data[12:14] == bytes([1, 0])
    path = tmp_path / "t.bsdf"
    path.write_bytes(data)
    back = render.read_tensor_file(path)
    assert list(back) == list(fields)
    assert bytes(back["description"]).decode() == "a staircase"
    for name, value in fields.items():
        if name != "description":
            assert back[name].dtype == value.dtype and back[name].shape == value.shape
            np.testing.assert_array_equal(back[name], value)


MATERIAL = render.Material("ggx", ((0.0, math.atan(0.07)),), 20.0, 150.0, (1.50, 1.46, 1.44),
                           0.03)  # fmt: skip
SHARP = MATERIAL._replace(edge_radius_um=0.0)


@pytest.fixture(scope="module")
def mi() -> object:
    """Mitsuba, or the test is skipped (the render extra)."""
    return pytest.importorskip("mitsuba", reason="mitsuba (the render extra) is not installed")


@pytest.fixture(scope="module")
def draft_table(mi, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, render.Resolution]:
    """Draft tables of the sharp staircase (the rounded one's arcs are interpolated from
    `arc_grid` when tabulated, checked on their own below)."""
    res = render.QUALITIES["draft"]
    path = tmp_path_factory.mktemp("bsdf") / "w35.bsdf"
    render.write_bsdf(path, SHARP, 35.0, res)
    return path, res


def measured_eval(path: Path, cameras: np.ndarray, lights: np.ndarray) -> np.ndarray:
    """Mitsuba's `measured` plugin (scalar_rgb) at each pair (local frame), (n, 3)."""
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    bsdf = mi.load_dict({"type": "measured", "filename": str(path)})
    ctx = mi.BSDFContext()
    out = []
    for c, lt in zip(cameras, lights, strict=True):
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*c)
        si.sh_frame = mi.Frame3f(mi.Vector3f(0.0, 0.0, 1.0))
        out.append(np.array(bsdf.eval(ctx, si, mi.Vector3f(*lt))))
    return np.array(out)


def test_measured_plugin_returns_the_model_at_the_table_nodes(mi, draft_table) -> None:
    """At a camera direction on the tables' parameter nodes and a light direction on the node of
    the sample square that Mitsuba's own warp sends there, Mitsuba's `measured` reads back the
    model's value (float32 tables: 1e-4), in all three channels (three indices)."""
    path, res = draft_table
    tables = render.read_tensor_file(path)
    warp_class = mi.scalar_rgb.MarginalContinuous2D0
    s = _rgl.grid(res.samples, res.samples).reshape(-1, 2)
    cams, lights = [], []
    for a, b in [(3, 2), (6, 5), (9, 7), (12, 4), (1, 6)]:
        cam = _rgl.spherical(tables["theta_i"][b].astype(float), tables["phi_i"][a].astype(float))
        warp = warp_class(np.ascontiguousarray(tables["vndf"][a, b]), normalize=True)
        for p in s[::37]:
            u = np.array(tuple(warp.sample(p)[0]))
            m = _rgl.spherical(_rgl.u_to_theta(u[0]), _rgl.u_to_phi(u[1]))
            light = 2.0 * (m @ cam) * m - cam
            if light[2] > 0.05:
                cams.append(cam)
                lights.append(light)
    cams, lights = np.array(cams), np.array(lights)
    got = measured_eval(path, cams, lights)
    want = render.mitsuba_value(SHARP, 35.0, cams, lights)
    big = want[:, 2] > 1e-3 * want.max()
    assert len(cams) > 40 and np.ptp(want[big, 0] / want[big, 2]) > 1e-3  # channels differ
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6 * want.max())


def test_vectorised_warp_is_mitsubas(mi, draft_table) -> None:
    """`_warp.sample_continuous` (the tables' nodes, many at once) is Mitsuba's
    `MarginalContinuous2D0.sample`: on every visible-normal table of the draft file and on a
    random bumpy density, most warped nodes are bit-identical (90% measured) and the rest
    differ by float32 rounding, which Mitsuba's own `invert` undoes as well as for its own
    warped nodes (both return the node within 2e-5 where the CDF is flat)."""
    from stairfit.render import _warp

    path, res = draft_table
    vndf = render.read_tensor_file(path)["vndf"]
    rng = np.random.default_rng(3)
    bumpy = (np.exp(3.0 * rng.random((40, 30))) * (rng.random((40, 30)) > 0.2)).astype(np.float32)
    tables = [vndf[a, b] for a in range(vndf.shape[0]) for b in range(0, vndf.shape[1], 2)]
    s = np.concatenate([_rgl.grid(res.samples, res.samples).reshape(-1, 2),
                        rng.random((200, 2)), [[0.0, 0.0], [1.0, 1.0], [0.0, 1.0]]])  # fmt: skip
    same, n, ours_back, own_back = 0, 0, 0.0, 0.0
    for table in [*tables, bumpy]:
        warp = mi.scalar_rgb.MarginalContinuous2D0(np.ascontiguousarray(table), normalize=True)
        ref = [warp.sample(p) for p in s]
        u_ref = np.array([tuple(d[0]) for d in ref], np.float32)
        pdf_ref = np.array([d[1] for d in ref], np.float32)
        u, pdf = _warp.sample_continuous(table, s)
        assert u.dtype == np.float32 and u.shape == (len(s), 2) and pdf.shape == (len(s),)
        exact = np.all(u == u_ref, axis=1)
        same, n = same + exact.sum(), n + len(s)
        # the density, a float32 interpolation, to rounding (it cancels where it is tiny)
        np.testing.assert_allclose(pdf[exact], pdf_ref[exact], rtol=1e-5,
                                   atol=1e-6 * pdf_ref.max())  # fmt: skip
        held = np.clip(s, _warp.EPSILON, _warp.ONE_MINUS_EPSILON)
        ours_back = max(ours_back, max(np.abs(np.array(tuple(warp.invert(p)[0])) - q).max()
                                       for p, q in zip(u, held, strict=True)))  # fmt: skip
        own_back = max(own_back, max(np.abs(np.array(tuple(warp.invert(p)[0])) - q).max()
                                     for p, q in zip(u_ref, held, strict=True)))  # fmt: skip
    assert same / n > 0.85
    assert ours_back < max(2.0 * own_back, 1e-6) and ours_back < 1e-4


def test_arc_grid_interpolates_the_rounded_edges_lobes() -> None:
    """The tables take the rounded edges' lobes from `arc_grid` (their costly part): over random
    pairs the radiance it gives (density times the light's cosine) is within 1.5% of the exact
    model's, summed (0.6% measured; a grid of half the nodes gave 1.7%)."""
    rng = np.random.default_rng(0)
    v = rng.normal(size=(2, 6000, 3))
    v[..., 2] = np.abs(v[..., 2])
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    w_i, w_o = v
    exact = render.density(MATERIAL, 30.0, w_i, w_o)
    approx = render.density(MATERIAL, 30.0, w_i, w_o, render.arc_grid(MATERIAL, 30.0))
    weight = w_i[:, 2:3]
    error = np.abs(approx - exact) * weight
    assert error.sum() / (exact * weight).sum() < 0.015
    assert np.abs(approx - exact).max() > 0.0  # interpolated, not the exact model again


def lobe_pairs(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Camera directions uniform on the hemisphere (elevation below 80 deg) and light
    directions drawn about the staircase's lobes (`render.Mixture`), local frame."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(4 * n, 3))
    v[:, 2] = np.abs(v[:, 2])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    cams = v[v[:, 2] > math.cos(math.radians(80.0))][:n]
    face = _rgl.to_face(cams)
    light, _ = render.Mixture(SHARP, 35.0, face, "light").sample(rng.random(n), rng.random((n, 2)))
    ok = light[:, 2] > 0.02
    return cams[ok], _rgl.to_local(light[ok])


@pytest.mark.slow
def test_tabulation_error_shrinks_as_the_tables_grow(mi, tmp_path: Path) -> None:
    """Between the nodes the reconstruction interpolates: over light directions near the lobes
    (sharp GGX staircase, 35-deg wedge), the summed absolute error relative to the summed value
    falls from the draft tables to the default ones, and is below 10% there
    (benchmarks/results/render_tables.md has the figures)."""
    cams, lights = lobe_pairs(1500, 3)
    want = render.mitsuba_value(SHARP, 35.0, cams, lights)
    errors = []
    for name in ("draft", "default"):
        path = tmp_path / f"{name}.bsdf"
        render.write_bsdf(path, SHARP, 35.0, render.QUALITIES[name])
        got = measured_eval(path, cams, lights)
        errors.append(np.abs(got - want).sum() / want.sum())
    assert errors[1] < 0.7 * errors[0], errors
    assert errors[1] < 0.10, errors
