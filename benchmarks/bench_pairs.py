"""Pair selection benchmark: the pairs chosen by footprint overlap from the rough POS (``hmcc
pairs``, the paper's rule) against COLMAP's exhaustive and spatial matching, by what matching
costs and what incremental mapping makes of the matches (issue 31).

Per flight, COLMAP's SIFT (pycolmap, CPU, default options but ``max_image_size``, one shared
camera; the EXIF GPS in the database's pose priors) once, then on a copy of that database per
row, COLMAP's matcher with its default options (SIFT matching and COLMAP's geometric
verification, CPU):

* **exhaustive**: ``pycolmap.match_exhaustive``, every pair;
* **spatial**: ``pycolmap.match_spatial`` with its defaults (the 50 nearest cameras within
  100 m, by GPS distance, heights ignored);
* **footprint**: ``hmcc pairs`` (overlap above 0.5 of the smaller footprint, POS from
  EXIF/XMP, cameras from EXIF), then ``pycolmap.match_image_pairs`` on that list; its time
  includes choosing the pairs;
* **footprint, database cameras**: the same with ``--database``, the cameras COLMAP's feature
  extractor wrote (its prior focal length, from its own sensor table);
* **footprint, 4 partners** (and with database cameras): the same with ``--min-partners 4``,
  every image keeping at least its 4 largest overlaps (above zero) besides those above half.
  Chosen on Brighton (the smallest of 2-6 that met the target there, mapping subsets of its
  exhaustive matches); Caliterra is held out;

then ``pycolmap.incremental_mapping`` on each: models, registered images, 3-D points, mean
reprojection error of the largest model.

Flights: Brighton Beach (18 DJI images, attitude in XMP, the ground at the take-off point from
``RelativeAltitude``) and Caliterra (75 images, GPS only: attitudes estimated from the track;
no height above ground in the tags). For Caliterra the flying height is estimated from the
exhaustive row's model: its scale from the horizontal GPS distances between the registered
cameras (median ratio over capture-consecutive pairs), times the median depth of each image's
3-D points (the camera looks down). Stated in the results; ``--flying-height`` overrides it.

``--service``: what ``POST /v1/pairs`` costs on the simulated 750-image penta-view flight
(:mod:`hmcc.simulate_flight`'s defaults, the paper's dataset 3: nadir and four 45 deg
obliques at 300 m, the ground at 0 m): the body's size, the library's time (parsing, then
choosing) and the service's answer through the app in process (``httpx.ASGITransport``),
each the median of 5 runs after one warm-up.

The machine is a shared 2-core one: times are single runs, noisy. Results go to
``<out>/pairs.json`` and ``<out>/pairs.md``. Usage (from the checkout's root)::

    .venv/bin/python -m benchmarks.bench_pairs --flights brighton --max-image-size 1200
    .venv/bin/python -m benchmarks.bench_pairs --flights caliterra --max-image-size 1000
    .venv/bin/python -m benchmarks.bench_pairs --service

(a flight run alone replaces its entry in ``pairs.json`` and keeps the others and the
service's; ``--service`` replaces the service's and keeps the flights).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sqlite3
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from hmcc.pose import geodetic_to_enu
from hmcc_colmap.pairs import choose_pairs, write_pairs_file
from hmcc_colmap.poses import read_image_poses

from .common import DEFAULT_FIXTURES, DEFAULT_OUT, environment, fmt, jsonable, with_code_hash

FLIGHTS = {
    "brighton": DEFAULT_FIXTURES / "images",
    "caliterra": DEFAULT_FIXTURES.parent / "caliterra" / "images",
}
#: --quick: five images of strips 1 and 2 (bench_colmap's), small.
QUICK_IMAGES = ("DJI_0024.JPG", "DJI_0025.JPG", "DJI_0033.JPG", "DJI_0034.JPG", "DJI_0035.JPG")
QUICK_IMAGE_SIZE = 600
ROWS = (
    "exhaustive",
    "spatial",
    "footprint",
    "footprint, database cameras",
    "footprint, 4 partners",
    "footprint, database cameras, 4 partners",
)
#: ``--min-partners`` of the rows that name it (chosen on Brighton, see the module doc).
PARTNERS = 4


def features(images: Path, db: Path, max_size: int) -> float:
    """COLMAP's SIFT of ``images`` into ``db``; the seconds it took."""
    t0 = time.perf_counter()
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = max_size
    pycolmap.extract_features(
        db,
        images,
        camera_mode=pycolmap.CameraMode.SINGLE,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    return time.perf_counter() - t0


def match(
    row: str, db: Path, images: Path, scratch: Path, flying_height: float | None = None
) -> dict[str, Any]:
    """One row's matching on ``db``: its seconds (and the footprint row's pair choice)."""
    out: dict[str, Any] = {}
    t0 = time.perf_counter()
    if row == "exhaustive":
        pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
    elif row == "spatial":
        pycolmap.match_spatial(db, device=pycolmap.Device.cpu)
    else:
        database = db if "database cameras" in row else None
        choice = choose_pairs(
            images,
            database=database,
            min_overlap=0.5,
            flying_height=flying_height,
            min_partners=PARTNERS if row.endswith("partners") else 0,
        )
        pairs_file = scratch / "pairs.txt"
        write_pairs_file(pairs_file, choice.pairs)
        out["choose_s"] = time.perf_counter() - t0
        out["ground"] = choice.ground
        out["estimated_attitudes"] = len(choice.estimated)
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = str(pairs_file)
        pycolmap.match_image_pairs(db, pairing_options=pairing, device=pycolmap.Device.cpu)
    out["matching_s"] = time.perf_counter() - t0
    return out


def counts(db: Path) -> dict[str, int]:
    con = sqlite3.connect(db)
    try:
        matched, raw = con.execute(
            "SELECT COUNT(*), COALESCE(SUM(rows), 0) FROM matches"
        ).fetchone()
        verified, inliers = con.execute(
            "SELECT COUNT(*), COALESCE(SUM(rows), 0) FROM two_view_geometries WHERE rows > 0"
        ).fetchone()
    finally:
        con.close()
    return {
        "matched_pairs": matched,
        "raw_matches": raw,
        "verified_pairs": verified,
        "inlier_matches": inliers,
    }


def mapping(db: Path, images: Path, out: Path) -> tuple[dict[str, Any], Any]:
    """Incremental mapping's figures of the largest model, and that model."""
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    models = pycolmap.incremental_mapping(db, images, out, pycolmap.IncrementalPipelineOptions())
    seconds = time.perf_counter() - t0
    if not models:
        return {"models": 0, "registered": 0, "mapping_s": seconds}, None
    best = max(models.values(), key=lambda m: m.num_reg_images())
    return {
        "models": len(models),
        "registered": best.num_reg_images(),
        "points3d": best.num_points3D(),
        "reprojection_error_px": best.compute_mean_reprojection_error(),
        "track_length": best.compute_mean_track_length(),
        "mapping_s": seconds,
    }, best


def flying_height(model: Any, images: Path) -> float:
    """The flying height (m) from a model and the images' GPS: see the module doc."""
    regs = sorted(model.images.values(), key=lambda im: im.name)
    names = [im.name for im in regs]
    poses = read_image_poses(images, names)
    lat, lon, alt = (np.array([poses[n].position[k] for n in names]) for k in ("lat", "lon", "alt"))  # type: ignore[index]
    enu = geodetic_to_enu(lat, lon, alt, (float(lat.mean()), float(lon.mean()), 0.0))
    centres = np.array([im.projection_center() for im in regs])
    ratios = []
    for k in range(len(regs) - 1):
        model_d = np.linalg.norm(centres[k + 1] - centres[k])
        gps_d = np.hypot(*(enu[k + 1, :2] - enu[k, :2]))
        if model_d > 0 and gps_d > 3.0:  # GNSS noise dominates shorter steps
            ratios.append(gps_d / model_d)
    depths = []
    for im in regs:
        pose = im.cam_from_world()
        xyz = np.array([model.points3D[p.point3D_id].xyz for p in im.points2D if p.has_point3D()])
        if len(xyz):
            depths.append(float(np.median((pose * xyz)[:, 2])))
    return float(np.median(ratios) * np.median(depths))


def service_cost(repeats: int = 5) -> dict[str, Any]:
    """``POST /v1/pairs`` on the simulated 750-image flight (see the module doc)."""
    import asyncio
    import statistics

    import httpx

    from hmcc.simulate_flight import FlightOptions, simulate_flight
    from hmcc_schema import parse_pairs
    from hmcc_service.app import create_app
    from hmcc_service.settings import Settings

    flight = simulate_flight(FlightOptions(keypoints_per_image=8, pairs=1), seed=0)
    images = {
        name: {k: v for k, v in image.items() if k in ("camera", "pose")}
        for name, image in flight.body["images"].items()
    }
    body = json.dumps({"images": images, "ground_z": 0.0}).encode()

    def library() -> tuple[float, float, int]:
        t0 = time.perf_counter()
        query = parse_pairs(body)
        t1 = time.perf_counter()
        chosen = query.choose()
        return t1 - t0, time.perf_counter() - t1, len(chosen.pairs)

    async def served() -> list[float]:
        app = create_app(Settings())
        seconds = []
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://b") as client:
            for _ in range(repeats + 1):
                t0 = time.perf_counter()
                r = await client.post(
                    "/v1/pairs", content=body, headers={"content-type": "application/json"}
                )
                r.raise_for_status()
                seconds.append(time.perf_counter() - t0)
        await app.state.queue.close()
        return seconds[1:]

    runs = [library() for _ in range(repeats + 1)][1:]
    http = asyncio.run(served())
    return {
        "images": len(images),
        "views": sorted(set(flight.image_views.values())),
        "body_bytes": len(body),
        "pairs": runs[0][2],
        "simulated_pairs": FlightOptions().pairs,
        "parse_s": statistics.median(r[0] for r in runs),
        "choose_s": statistics.median(r[1] for r in runs),
        "http_s": statistics.median(http),
        "repeats": repeats,
    }


def run_flight(
    name: str, images: Path, tmp: Path, max_size: int, given_height: float | None
) -> dict[str, Any]:
    base = tmp / f"{name}-features.db"
    extract_s = features(images, base, max_size)
    print(f"{name}: features in {extract_s:.1f} s")
    rows: list[dict[str, Any]] = []
    height_note = None
    for row in ROWS:
        stem = f"{name}-{row.replace(', ', '-').replace(' ', '_')}"
        db = tmp / f"{stem}.db"
        shutil.copy(base, db)
        scratch = tmp / stem
        scratch.mkdir()
        if row.startswith("footprint") and name == "caliterra" and height_note is None:
            if given_height is None:
                exhaustive_model = rows[0].pop("_model")
                given_height = flying_height(exhaustive_model, images)
                height_note = "estimated from the exhaustive row's model and the GPS"
            else:
                height_note = "given (--flying-height)"
        figures = {
            "row": row,
            **match(
                row, db, images, scratch, given_height if row.startswith("footprint") else None
            ),
            **counts(db),
        }
        mapped, model = mapping(db, images, scratch / "sparse")
        figures.update(mapped)
        if row == "exhaustive":
            figures["_model"] = model
        rows.append(figures)
        print(json.dumps(jsonable({k: v for k, v in figures.items() if k != "_model"})))
    for r in rows:
        r.pop("_model", None)
    exhaustive = rows[0]
    for r in rows:
        r["matching_vs_exhaustive"] = r["matching_s"] / exhaustive["matching_s"]
    return {
        "flight": name,
        "max_image_size": max_size,
        "images": len([p for p in images.iterdir() if p.is_file()]),
        "features_s": extract_s,
        "flying_height_m": given_height,
        "flying_height_note": height_note,
        "rows": rows,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--flights", nargs="+", choices=sorted(FLIGHTS), default=list(FLIGHTS))
    p.add_argument("--out", type=Path, default=DEFAULT_OUT)
    p.add_argument("--max-image-size", type=int, default=1200)
    p.add_argument("--flying-height", type=float, help="Caliterra's flying height, m")
    p.add_argument("--quick", action="store_true", help="5 Brighton images at 600 px (smoke)")
    p.add_argument(
        "--service", action="store_true", help="only POST /v1/pairs on a simulated 750-image flight"
    )
    args = p.parse_args(argv)
    previous = args.out / "pairs.json"
    earlier = json.loads(previous.read_text()) if previous.is_file() else {}
    if args.service:
        cost = service_cost()
        print(json.dumps(cost))
        doc = {**earlier, "service": cost}
        doc.pop("code_hash", None)
        doc["meta"] = {
            "pycolmap": pycolmap.__version__,
            "note": "shared, noisy 2-core machine; single runs",
            **doc.get("meta", {}),
            "service_environment": environment(),
        }
        doc.setdefault("flights", [])
        return _write(args.out, doc)
    flights = []
    with tempfile.TemporaryDirectory(prefix="hmcc-bench-pairs-") as tmp:
        if args.quick:
            images = Path(tmp) / "images"
            images.mkdir()
            for name in QUICK_IMAGES:
                shutil.copy(FLIGHTS["brighton"] / name, images / name)
            flights.append(run_flight("brighton", images, Path(tmp), QUICK_IMAGE_SIZE, None))
        for name in [] if args.quick else args.flights:
            flights.append(
                run_flight(
                    name,
                    FLIGHTS[name],
                    Path(tmp),
                    args.max_image_size,
                    args.flying_height if name == "caliterra" else None,
                )
            )
    # a flight run alone replaces its own entry of an earlier results file, keeps the others
    kept = earlier.get("flights", [])
    ran = {f["flight"] for f in flights}
    flights = [f for f in kept if f["flight"] not in ran] + flights
    flights.sort(key=lambda f: list(FLIGHTS).index(f["flight"]))
    doc = {
        "meta": {
            **environment(),
            "pycolmap": pycolmap.__version__,
            "note": "shared, noisy 2-core machine; single runs",
            "quick": args.quick,
        },
        "flights": flights,
    }
    if "service" in earlier:
        doc["service"] = earlier["service"]
    return _write(args.out, doc)


def _write(out: Path, doc: dict[str, Any]) -> int:
    out.mkdir(parents=True, exist_ok=True)
    (out / "pairs.json").write_text(
        json.dumps(jsonable(with_code_hash(doc, __file__)), indent=2) + "\n"
    )
    (out / "pairs.md").write_text(markdown(doc))
    print(markdown(doc))
    return 0


def markdown(doc: dict[str, Any]) -> str:
    meta = doc["meta"]
    lines = [
        "# Pair selection: footprint overlap against COLMAP's exhaustive and spatial matching "
        "(issue 31)",
        "",
        "COLMAP SIFT (default options but the image size) and COLMAP's matcher with its defaults "
        f"(pycolmap {meta['pycolmap']}, CPU), then `pycolmap.incremental_mapping`; the "
        "footprint rows' matching time includes `hmcc pairs` choosing the pairs (overlap above "
        "0.5 of the smaller footprint; the `4 partners` rows also keep every image's 4 largest "
        "overlaps, `--min-partners 4`, chosen on Brighton, Caliterra held out). The target: "
        "the same registered images and at least 95 % of spatial matching's 3-D points with at "
        f"most half its pairs. {meta['note']}. Reproduce: "
        "`.venv/bin/python -m benchmarks.bench_pairs --flights brighton --max-image-size 1200`, "
        "then `--flights caliterra --max-image-size 1000`.",
    ]
    for f in doc["flights"]:
        lines += [
            "",
            f"## {f['flight']} ({f['images']} images, SIFT at {f['max_image_size']} px)",
            "",
        ]
        if f["flying_height_m"] is not None:
            lines += [
                f"Flying height {f['flying_height_m']:.1f} m ({f['flying_height_note']}).",
                "",
            ]
        lines += [
            "| pairs | matched pairs | x spatial | verified pairs | matching (s) | x exhaustive | "
            "models | registered | 3-D points | x spatial | reproj. error (px) | track length |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        spatial = next((r for r in f["rows"] if r["row"] == "spatial"), None)
        for r in f["rows"]:
            pairs_ratio = points_ratio = None
            if spatial is not None:
                pairs_ratio = r["matched_pairs"] / max(spatial["matched_pairs"], 1)
                points_ratio = r.get("points3d", 0) / max(spatial.get("points3d", 0), 1)
            lines.append(
                f"| {r['row']} | {r['matched_pairs']} | {fmt(pairs_ratio, 2)} | "
                f"{r['verified_pairs']} | "
                f"{r['matching_s']:.1f} | {fmt(r['matching_vs_exhaustive'], 2)} | "
                f"{r.get('models', '-')} | {r.get('registered', '-')} | "
                f"{r.get('points3d', '-')} | {fmt(points_ratio, 3)} | "
                f"{fmt(r.get('reprojection_error_px'), 3)} | "
                f"{fmt(r.get('track_length'), 2)} |"
            )
        for foot in (r for r in f["rows"] if r["row"].startswith("footprint")):
            lines += [
                "",
                f"{foot['row']}: ground {foot['ground']}; pairs chosen in "
                f"{foot['choose_s']:.2f} s; {foot['estimated_attitudes']} attitudes estimated "
                "from the track.",
            ]
    if (svc := doc.get("service")) is not None:
        lines += [
            "",
            f"## POST /v1/pairs on a simulated {svc['images']}-image flight",
            "",
            f"The paper's dataset 3 simulated ({', '.join(svc['views'])} views at 300 m): a "
            f"{svc['body_bytes'] / 1e6:.2f} MB JSON body, {svc['pairs']} pairs chosen (the "
            f"simulation's own list has the {svc['simulated_pairs']} pairs sharing most "
            "points). Medians of "
            f"{svc['repeats']} runs: parsing {svc['parse_s'] * 1e3:.0f} ms, choosing "
            f"{svc['choose_s'] * 1e3:.0f} ms (footprints and overlaps), the whole request "
            f"through the app {svc['http_s'] * 1e3:.0f} ms.",
        ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
