"""How well `stairfit init` (issue 44) drafts a scene: view angles, focal length, and the fit.

For each photo set whose truth is known, its DNGs are copied to a fresh folder (its scene.toml
and truth.json left behind) and drafted by `stairfit init` with the lamp angles and a layout
made of the original scene's own [specimen], [markers], [light] and [camera] tables (the
[camera] without its focal length, which init then estimates). Reported per photo: the
estimated view angle against the scene's, and the focal length against the truth. With `--fit`
both scenes are fitted (`stairfit fit --no-posterior`, the same options) and every parameter's
difference is given in standard errors of the original's fit; with `--true-views` also the
draft with the original's view angles written in (what the rest of the draft does to the fit).

The sets: `simulate` (tests/app/test_init.py's folder: 1.5 MP, 6 views, HDR brackets of 2, a flat
field and a dark frame; a parallel projection), `independent` (tests/independent_photos.py's
standing wedges, a pinhole at 900 mm) and, given `--pbr DIR`, the physically based dev set
(benchmarks/make_pbr_set.py --set dev; its folder is only read, and its `[extraction]`, not a
layout table, is copied into the draft as a user keeps their extraction settings).

    python benchmarks/bench_init.py [--fit] [--true-views] [--pbr DIR] [--keep DIR]
        [--fit-args "--model rounded+floor"] [--sets simulate,independent,pbr-dev]

Results: benchmarks/results/init.md (newest run first).
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

import tomli_w

TESTS = Path(__file__).resolve().parents[1] / "tests"
SIMULATED = ["--megapixels", "1.5", "--views", "6", "--bracket", "2", "--flat-field", "1",
             "--dark-frames", "1"]  # fmt: skip


def _stairfit(*args: str) -> float:
    """Wall seconds of one `stairfit` process (failures raise with its error)."""
    t0 = time.perf_counter()
    proc = subprocess.run(["stairfit", *args], capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"stairfit {' '.join(args)}: {proc.stderr.strip()[-2000:]}")
    return time.perf_counter() - t0


def _layout(scene: Path, out: Path) -> Path:
    raw = tomllib.loads(scene.read_text())
    layout = {k: raw[k] for k in ("specimen", "markers", "light", "camera") if k in raw}
    for key in ("focal_length_px", "principal_point_px"):
        layout["camera"].pop(key, None)
    out.write_text(tomli_w.dumps(layout))
    return out


def _draft(original: Path, work: Path, name: str) -> tuple[Path, float]:
    """A copy of the set's DNGs drafted by init from the lamp angles and the layout."""
    photos = work / f"{name}-draft"
    photos.mkdir()
    for f in original.glob("*.dng"):
        shutil.copy2(f, photos / f.name)
    raw = tomllib.loads((original / "scene.toml").read_text())
    table = work / f"{name}-angles.csv"
    rows = [f"{p['file'] if isinstance(p['file'], str) else p['file'][0]},{p['light_deg']}"
            for p in raw["photos"]]  # fmt: skip
    table.write_text("file,light_deg\n" + "\n".join(rows) + "\n")
    layout = _layout(original / "scene.toml", work / f"{name}-layout.toml")
    seconds = _stairfit("init", str(photos), "--angles", str(table), "--layout", str(layout),
                        "--quiet")  # fmt: skip
    if "extraction" in raw:  # not a layout table: the user keeps their extraction settings
        with open(photos / "scene.toml", "a") as fh:
            fh.write("\n" + tomli_w.dumps({"extraction": raw["extraction"]}))
    return photos, seconds


def _views(folder: Path) -> dict[str, float]:
    raw = tomllib.loads((folder / "scene.toml").read_text())
    return {(p["file"] if isinstance(p["file"], str) else p["file"][0]): p["view_deg"]
            for p in raw["photos"]}  # fmt: skip


def _with_views(draft: Path, views: dict[str, float], out: Path) -> Path:
    """A copy of the draft with the given view angles written in."""
    shutil.copytree(draft, out, ignore=shutil.ignore_patterns(".stairfit-cache"))
    text = (out / "scene.toml").read_text()
    parts = text.split("[[photos]]")
    for k, part in enumerate(parts[1:], start=1):
        first = re.search(r'^file = (?:\["([^"]+)"|"([^"]+)")', part, flags=re.M)
        name = first.group(1) or first.group(2)
        parts[k] = re.sub(r"^view_deg = .*$", f"view_deg = {views[name]}", part, flags=re.M)
    (out / "scene.toml").write_text("[[photos]]".join(parts))
    return out


def _fit(folder: Path, out: Path, extra: list[str]) -> tuple[dict, float]:
    seconds = _stairfit("fit", str(folder), "-o", str(out), "--no-posterior", "--quiet", *extra)
    return json.loads((out / "results.json").read_text()), seconds


def _differences(a: dict, b: dict) -> list[str]:
    """One table row per parameter: the original's value +- stderr, the other's, the difference
    in the original's standard errors."""
    other = {(p["name"], p.get("wedge")): p for p in b["parameters"]}
    rows = []
    for p in a["parameters"]:
        q = other.get((p["name"], p.get("wedge")))
        va, se = p["least_squares"]["value"], p["least_squares"]["stderr"]
        if q is None:
            rows.append(f"| {p['name']} | {va:.6g} +- {se:.3g} | (not fitted) | |")
            continue
        vb = q["least_squares"]["value"]
        rows.append(f"| {p['name']} | {va:.6g} +- {se:.3g} | {vb:.6g} | {(vb - va) / se:+.2f} |")
    return rows


def _report_set(name: str, original: Path, work: Path, args: argparse.Namespace) -> list[str]:
    draft, seconds = _draft(original, work, name)
    truth, drafted = _views(original), _views(draft)
    errors = {f: drafted[f] - truth[f] for f in truth}
    lines = [f"### {name}", "", f"init: {seconds:.1f} s wall.", ""]
    focal = tomllib.loads((draft / "scene.toml").read_text())["camera"].get("focal_length_px")
    known = tomllib.loads((original / "scene.toml").read_text())["camera"].get("focal_length_px")
    lines += [f"Focal length: {focal} px (scene: {known}).", ""]
    lines += ["| photo | view_deg | estimated | error |", "|---|---|---|---|"]
    lines += [f"| {f} | {truth[f]:g} | {drafted[f]:g} | {errors[f]:+.3f} |" for f in truth]
    worst = max(abs(e) for e in errors.values())
    lines += ["", f"Largest view-angle error: {worst:.3f} deg.", ""]
    if args.fit:
        copy = work / f"{name}-original"  # the fit writes its cache beside the photos
        if not copy.exists():
            copy.mkdir()
            for f in (*original.glob("*.dng"), original / "scene.toml"):
                shutil.copy2(f, copy / f.name)
        extra = args.fit_args.split()
        base, t0 = _fit(copy, work / f"{name}-original-fit", extra)
        other, t1 = _fit(draft, work / f"{name}-draft-fit", extra)
        chosen = (base["model_selection"]["chosen"], other["model_selection"]["chosen"])
        lines += [f"Fits ({t0:.0f} s, {t1:.0f} s): chosen {chosen[0]} (original), {chosen[1]} "
                  "(draft).", "", "| parameter | original | draft | difference (se) |",
                  "|---|---|---|---|", *_differences(base, other), ""]  # fmt: skip
        if args.true_views:
            fixed = _with_views(draft, truth, work / f"{name}-draft-true-views")
            third, t2 = _fit(fixed, work / f"{name}-true-views-fit", extra)
            lines += [f"The draft with the scene's view angles ({t2:.0f} s): chosen "
                      f"{third['model_selection']['chosen']}.", "",
                      "| parameter | original | draft, true views | difference (se) |",
                      "|---|---|---|---|", *_differences(base, third), ""]  # fmt: skip
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--fit", action="store_true", help="fit the original and the draft")
    parser.add_argument("--true-views", action="store_true", help="also the draft, true views")
    parser.add_argument("--pbr", type=Path, default=None, help="the physically based dev set")
    parser.add_argument("--keep", type=Path, default=None, help="work here (kept) instead")
    parser.add_argument("--fit-args", default="", help="more options of the fits, e.g. --model X")
    parser.add_argument("--sets", default="simulate,independent,pbr-dev", help="which sets")
    args = parser.parse_args()
    work = args.keep or Path(tempfile.mkdtemp(prefix="bench-init-"))
    work.mkdir(parents=True, exist_ok=True)
    sys.path.insert(0, str(TESTS))
    import independent_photos as ip

    wanted = set(args.sets.split(","))
    sets = {}
    if "simulate" in wanted:
        _stairfit("simulate", str(work / "simulate"), *SIMULATED, "--quiet")
        sets["simulate"] = work / "simulate"
    if "independent" in wanted:
        ip.render_folder(work / "independent", setup=ip.standing_setup(), seed=1)
        sets["independent"] = work / "independent"
    if args.pbr is not None and "pbr-dev" in wanted:
        sets["pbr-dev"] = args.pbr
    lines = []
    for name, folder in sets.items():
        lines += _report_set(name, folder, work, args)
    print("\n".join(lines))
    if args.keep is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
