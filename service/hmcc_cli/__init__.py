"""The ``hmcc`` command line: ``verify``, ``plot`` and ``simulate`` (the core through the JSON
contract), ``flight`` (a whole flight, here or through a service), ``colmap`` (a COLMAP
database), ``pairs`` (the pairs to match, from the rough POS), ``match`` (a COLMAP database's
matching, guided by the rough POS), ``serve``, ``worker`` and ``loadtest`` (the service).

The top of the package graph: it may import every package of the project, and nothing imports
it. Service modules are imported when their command runs, so ``hmcc verify`` starts quickly.

Exit codes: 0 success, 2 bad input (each problem printed as ``error: <field>: <reason>``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

# One BLAS thread in ``hmcc flight``'s process, set before numpy is imported: OpenBLAS starts a
# thread a core there that spins some 0.1 CPU s for nothing (9 % of the command's own CPU on the
# benchmark flight), where the process only reads, checks and writes and its children use one
# BLAS thread each (hmcc_worker.pool.prepare_process). A flight verified in this process gets
# the same results (checked on 4 000 pairs), with less CPU. The user's own setting wins.
if sys.argv[1:2] == ["flight"]:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    # The children's fork server, started before this package's imports (hmcc_cli.flight_args).
    from .flight_args import start_early

    start_early(sys.argv[2:])

from pydantic import ValidationError

from hmcc import InputError
from hmcc.method_names import METHOD_NAMES as METHODS
from hmcc_schema import is_reference_pair, parse_pair, reference_to_pair, validation_issues

from .extras import install_hint
from .outputs import checked_output

__all__ = ["main"]

#: What ``hmcc --help`` says (the module's docstring is for the project's developers).
DESCRIPTION = """\
Verify the candidate matches of UAV image pairs with the images' rough POS (HMCC-RANSAC):
the inlier matches, the fitted model, per-stage timings and statistics; for one pair, a
whole flight or a COLMAP database, here or through the HTTP service it also runs.

Exit codes: 0 done; 2 bad input, each problem on standard error as
"error: <field>: <reason>"; 1 a service (--url) failed or could not be reached.
"hmcc COMMAND --help" tells a command's options.
"""


def _load(path: str) -> Any:
    text = sys.stdin.read() if path == "-" else Path(path).read_text()
    return json.loads(text)


def _summary(doc: dict[str, Any], result: dict[str, Any]) -> str:
    stats = result["statistics"]
    lines = [
        f"method {result['method']}: {stats['inliers']} of {stats['matches']} matches are "
        f"inliers ({stats['inlier_ratio']:.1%}), {result['timings_ms']['total']:.2f} ms",
    ]
    if "z0_m" in stats:
        ground = result["stages"][0]["stats"].get("ground_z_m")
        below = "" if ground is None else f" ({ground - stats['z0_m']:.2f} m below the ground)"
        lines.append(f"plane Z0 = {stats['z0_m']:.2f} m{below}")
    lines.append(f"{'stage':<17}{'in':>7}{'kept':>7}{'ms':>9}")
    for s in result["stages"]:
        lines.append(f"{s['name']:<17}{s['input']:>7}{s['kept']:>7}{s['time_ms']:>9.3f}")
    truth = (doc.get("ground_truth") or {}).get("inliers")
    if truth is not None:
        found, true = set(result["inliers"]), set(truth)
        hit = len(found & true)
        lines.append(
            f"vs ground truth: precision {hit / max(len(found), 1):.3f}, "
            f"recall {hit / max(len(true), 1):.3f}"
        )
    if "degenerate" in stats:
        lines.append(f"degenerate: {stats['degenerate']}")
    return "\n".join(lines)


def _apply_overrides(doc: dict[str, Any], args: argparse.Namespace) -> None:
    if args.method:
        doc["method"] = args.method
    if args.plane_z is not None:
        try:
            doc["plane"] = {"z": args.plane_z if args.plane_z == "auto" else float(args.plane_z)}
        except ValueError:
            raise InputError("plane.z", "--plane-z must be a height in metres or 'auto'") from None
    if args.ground_z is not None:
        doc["plane"] = {"ground_z": args.ground_z}
    if args.seed is not None:
        params = doc.setdefault("params", {})
        if isinstance(params, dict):
            params["seed"] = args.seed


def _run_pair(args: argparse.Namespace, motions: bool) -> tuple[Any, dict[str, Any]] | None:
    """The pair file's document and its full result; None after printing the errors."""
    try:
        doc = _load(args.pair)
    except (OSError, json.JSONDecodeError) as e:
        print(f"error: {args.pair}: {e}", file=sys.stderr)
        return None
    try:
        if isinstance(doc, dict) and is_reference_pair(doc):
            doc = reference_to_pair(doc)
        if isinstance(doc, dict):
            _apply_overrides(doc, args)
            if motions:
                params = doc.setdefault("params", {})
                if isinstance(params, dict):
                    params["return_motions"] = True
                    params["result"] = "full"
        result = parse_pair(doc).verify(0).to_dict()
    except (ValidationError, InputError) as e:
        for issue in validation_issues(e):
            print(f"error: {issue.field}: {issue.reason}", file=sys.stderr)
        return None
    return doc, result


def _verify(args: argparse.Namespace) -> int:
    ran = _run_pair(args, motions=False)
    if ran is None:
        return 2
    doc, result = ran
    print(_summary(doc, result) if args.summary else json.dumps(result))
    return 0


def _plot(args: argparse.Namespace) -> int:
    import importlib.util

    if importlib.util.find_spec("matplotlib") is None:
        print(f"error: hmcc plot needs matplotlib: {install_hint('plot')}", file=sys.stderr)
        return 2
    from .plot import draw_motions

    output = checked_output(args.output, "--output")
    if output is None:
        return 2
    ran = _run_pair(args, motions=True)
    if ran is None:
        return 2
    doc, result = ran
    draw_motions(doc, result, output)
    print(f"wrote {args.output}", file=sys.stderr)
    return 0


def _simulate(args: argparse.Namespace) -> int:
    from hmcc.simulate import SimulationOptions, simulate_pair

    try:
        options = SimulationOptions(
            views=(args.views[0], args.views[1]),
            n_inliers=args.n_inliers,
            outlier_ratio=args.outlier_ratio,
            outlier_mode=args.outlier_mode,
            altitude_m=args.altitude,
            relief_m=args.relief,
        )
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    outputs: list[Path] = []
    if args.output is not None:
        for k in range(args.count):
            out = Path(args.output)
            if args.count > 1:
                out = out.with_name(f"{out.stem}_{args.seed + k:04d}{out.suffix}")
            checked = checked_output(out, "--output")
            if checked is None:
                return 2
            outputs.append(checked)
    for k in range(args.count):
        text = json.dumps(simulate_pair(options, seed=args.seed + k))
        if outputs:
            outputs[k].write_text(text)
        else:
            print(text)
    return 0


def _serve(args: argparse.Namespace) -> int:
    import os

    from hmcc_service.server import serve
    from hmcc_service.settings import get_settings

    if args.host:
        os.environ["HMCC_HOST"] = args.host
    if args.port:
        os.environ["HMCC_PORT"] = str(args.port)
    settings = get_settings()
    if args.workers > 1 and not settings.redis_url:
        print(
            "error: --workers > 1 needs REDIS_URL (embedded jobs live in one process)",
            file=sys.stderr,
        )
        return 2
    return serve(settings, args.workers)


def _worker(args: argparse.Namespace) -> int:
    from hmcc_service.settings import get_settings
    from hmcc_worker.logs import configure_logging
    from hmcc_worker.pool import ComputePool, ComputePoolDead
    from hmcc_worker.rq_worker import HmccWorker, make_worker, run_worker

    settings = get_settings()
    if not settings.redis_url:
        print("error: hmcc worker needs REDIS_URL (e.g. redis://127.0.0.1:6379/0)", file=sys.stderr)
        return 2
    configure_logging(settings.log_level)
    redis_url = settings.redis_url

    def make() -> HmccWorker:
        return make_worker(
            redis_url,
            settings.queue_name,
            job_timeout_s=settings.job_timeout_s,
            grace_s=settings.worker_grace_s,
            result_ttl_s=settings.result_ttl_s,
            name=args.name,
        )

    compute = ComputePool(1, timeout_s=settings.job_timeout_s)
    stopped_cleanly = False
    try:
        compute.start()
        run_worker(
            make,
            compute,
            redis_url=redis_url,
            burst=args.burst,
            logging_level=settings.log_level,
        )
        stopped_cleanly = True
    except ComputePoolDead as e:
        # Exit non-zero, so that a supervisor restarts the worker.
        print(f"error: {e}", file=sys.stderr)
        return 3
    finally:
        compute.close(wait=stopped_cleanly)
    return 0


def _loadtest(args: argparse.Namespace) -> int:
    from hmcc_service.loadtest import main as loadtest_main

    return loadtest_main(args)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="hmcc", description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = p.add_subparsers(dest="command", required=True, title="commands", metavar="COMMAND")

    v = sub.add_parser("verify", help="verify the matches of a pair file; prints JSON")
    v.add_argument("pair", help="pair file (public format or a shared/fixtures pair), - = stdin")
    v.add_argument("--method", choices=METHODS, help="override the file's method")
    v.add_argument("--plane-z", help="override the plane: metres (that plane) or 'auto'")
    v.add_argument("--ground-z", type=float, help="override: the ground height, metres")
    v.add_argument("--seed", type=int, help="override params.seed")
    v.add_argument("--summary", action="store_true", help="a human-readable summary")
    v.set_defaults(run=_verify)

    pl = sub.add_parser(
        "plot",
        help="draw a pair's motions by stage decision and its votes (PNG; needs the plot extra: "
        "scripts/bootstrap plot)",
    )
    pl.add_argument("pair", help="pair file (public format or a shared/fixtures pair), - = stdin")
    pl.add_argument("-o", "--output", required=True, help="the PNG to write")
    pl.add_argument("--method", choices=METHODS, help="override the file's method")
    pl.add_argument("--plane-z", help="override the plane: metres (that plane) or 'auto'")
    pl.add_argument("--ground-z", type=float, help="override: the ground height, metres")
    pl.add_argument("--seed", type=int, help="override params.seed")
    pl.set_defaults(run=_plot)

    s = sub.add_parser("simulate", help="write simulated pair files with ground truth")
    s.add_argument(
        "--views",
        nargs=2,
        default=["V", "V"],
        metavar=("VIEW1", "VIEW2"),
        help="V nadir, F front, B back, L left, R right (default V V)",
    )
    s.add_argument("--n-inliers", type=int, default=400)
    s.add_argument("--outlier-ratio", type=float, default=0.5)
    s.add_argument("--outlier-mode", choices=["uniform", "mismatch"], default="uniform")
    s.add_argument("--altitude", type=float, default=120.0, help="flying height, m")
    s.add_argument("--relief", type=float, default=15.0, help="terrain relief, m")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--count", type=int, default=1, help="pairs to write (seeds seed..)")
    s.add_argument("-o", "--output", help="output file (default stdout)")
    s.set_defaults(run=_simulate)

    sv = sub.add_parser("serve", help="run the HTTP API (settings: HMCC_* and REDIS_URL)")
    sv.add_argument("--host", help="bind address (HMCC_HOST, default 127.0.0.1)")
    sv.add_argument("--port", type=int, help="port (HMCC_PORT, default 8000)")
    sv.add_argument(
        "--workers", type=int, default=1, help="API processes (needs REDIS_URL when > 1)"
    )
    sv.set_defaults(run=_serve)

    w = sub.add_parser("worker", help="run one RQ worker (needs REDIS_URL); start N for N")
    w.add_argument("--burst", action="store_true", help="exit when the queue is empty")
    w.add_argument("--name", help="worker name (default hmcc-<host>-<pid>)")
    w.set_defaults(run=_worker)

    fl = sub.add_parser("flight", help="verify every pair of a flight file (here or via --url)")
    _add_flight_arguments(fl)
    fl.set_defaults(run=_flight)

    cf = sub.add_parser(
        "convert-flight", help="write a flight file as a binary one (MessagePack, raw arrays)"
    )
    cf.add_argument("input", help="flight file (JSON or binary), - = stdin")
    cf.add_argument("output", help="binary flight file (JSON when it ends in .json)")
    cf.add_argument(
        "--columns",
        action="store_true",
        help="the pairs as columns: the form hmcc flight reads fastest (every pair with its "
        "matches only; the service takes rows)",
    )
    cf.set_defaults(run=_convert_flight)

    cm = sub.add_parser(
        "colmap", help="verify the matches of a COLMAP database, write the geometries back"
    )
    _add_colmap_arguments(cm)
    cm.set_defaults(run=_colmap)

    pa = sub.add_parser(
        "pairs", help="choose the pairs to match from the rough POS (footprint overlap)"
    )
    _add_pairs_arguments(pa)
    pa.set_defaults(run=_pairs)
    mt = sub.add_parser(
        "match", help="match a COLMAP database's features guided by the rough POS (SIFT)"
    )
    _add_match_arguments(mt)
    mt.set_defaults(run=_match)

    lt = sub.add_parser("loadtest", help="load a running service on loopback; prints figures")
    _add_loadtest_arguments(lt)
    lt.set_defaults(run=_loadtest)
    return p


def _add_flight_arguments(parser: argparse.ArgumentParser) -> None:
    from .flight import add_arguments

    add_arguments(parser)


def _convert_flight(args: argparse.Namespace) -> int:
    from .flight import convert

    return convert(args)


def _flight(args: argparse.Namespace) -> int:
    from .flight import run

    return run(args)


def _add_colmap_arguments(parser: argparse.ArgumentParser) -> None:
    from .colmap import add_arguments

    add_arguments(parser)


def _colmap(args: argparse.Namespace) -> int:
    from .colmap import run

    return run(args)


def _add_pairs_arguments(parser: argparse.ArgumentParser) -> None:
    from .pairs import add_arguments

    add_arguments(parser)


def _add_match_arguments(parser: argparse.ArgumentParser) -> None:
    from .match import add_arguments

    add_arguments(parser)


def _pairs(args: argparse.Namespace) -> int:
    from .pairs import run

    return run(args)


def _match(args: argparse.Namespace) -> int:
    from .match import run

    return run(args)


def _add_loadtest_arguments(parser: argparse.ArgumentParser) -> None:
    from hmcc_service.loadtest import add_arguments

    add_arguments(parser)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    return int(args.run(args))


if __name__ == "__main__":
    sys.exit(main())
