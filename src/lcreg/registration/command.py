"""``lcreg register``: register two files, or many pairs, from the command line.

``lcreg register SRC REF`` prints the transform (source into reference), the fitness and inlier RMSE, the time, and
where it wrote files (``--out``, ``--save-aligned``, ``--plot``). ``lcreg register --pairs FILE`` registers every
pair of a CSV, a 3DMatch ``gt.log`` scene (or benchmark folder) or a KITTI pair list (:mod:`lcreg.registration.many`).

Errors print one line on stderr: exit code 2 for arguments, 1 for files, clouds and weights; nothing is written
then. ``LCREG_DEBUG=1`` shows the traceback.
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn

import numpy as np

from lcreg.checks import MissingDependencyError
from lcreg.methods import METHODS
from lcreg.registration.api import DEFAULT, DEFAULT_WITHOUT_KISS, Registration, register
from lcreg.registration.methods import CLASSICAL, LEARNED, MethodError
from lcreg.registration.outputs import TRANSFORM_SUFFIXES, check_suffix, read_transform, write_ply, write_transform
from lcreg.registration.voxel import TARGET_POINTS

__all__ = ["build_parser", "main", "run"]


def _methods_help() -> str:
    """The method list of ``--help``, with the shipped weights of each learned method."""
    from lcreg.weights import REGISTRY, shipped_names

    shipped = shipped_names()
    lines = [
        f"  default       {DEFAULT.describe()} (chosen on the validation pairs, docs/results/register.md); "
        f"{DEFAULT_WITHOUT_KISS.describe()} where kiss-matcher is not installed"
    ]
    lines += [f"  {name:<13} {text}" for name, text in CLASSICAL.items()]
    for name, class_path in LEARNED.items():
        names = [n for n in shipped if REGISTRY[n].class_path == class_path]
        weights = f"shipped weights: {', '.join(names)}" if names else "needs --weights (.ckpt or .pt)"
        lines.append(f"  {name:<13} {METHODS[name].summary}; {weights}")
    lines.append(
        "  (learned methods are object models: complete objects that overlap fully, any unit; on partial scans "
        "they fail, use ransac+icp or kiss+icp, or --fallback)"
    )
    lines.append("  X+icp         any of the above but icp, then ICP refinement (e.g. ransac+icp, fgr+icp, dvds+icp)")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``lcreg register``."""
    parser = argparse.ArgumentParser(
        prog="lcreg register",
        description="Register a source cloud onto a reference cloud (the transform maps source points into the "
        "reference frame), or many pairs with --pairs.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=f"methods:\n{_methods_help()}\n\nfiles: .ply .pcd .xyz .xyzn .xyzrgb .pts .npy and KITTI .bin\n"
        "example: lcreg register scan_a.ply scan_b.ply --out T.txt --plot before_after.png",
    )
    parser.add_argument("src", nargs="?", help="source cloud file (moved onto the reference)")
    parser.add_argument("ref", nargs="?", help="reference cloud file")
    parser.add_argument(
        "--pairs",
        help="many pairs: a CSV (src,ref[,16 gt numbers]), a 3DMatch scene folder or "
        "gt.log (or a benchmarks/3DMatch folder: all scenes), or a KITTI pairs/*.json list",
    )
    parser.add_argument("--method", default="default", help="method short name (see below); default: %(default)s")
    parser.add_argument("--weights", help="learned methods: a shipped name, an exported .pt or a .ckpt of lcreg fit")
    parser.add_argument("--refine", choices=("icp", "none"), help="add ICP refinement to a single-step method")
    parser.add_argument("--voxel-size", type=float, help="voxel size in the clouds' unit (default: automatic)")
    parser.add_argument(
        "--target-points",
        type=int,
        default=TARGET_POINTS,
        help="points per cloud after the automatic downsampling (default: %(default)s)",
    )
    parser.add_argument("--init", help="initial guess: a 4x4 transform file (.txt, .npy or .json)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the learned methods' point samples")
    parser.add_argument(
        "--threads",
        type=int,
        help="CPU threads of Open3D and torch (default: theirs, all cores); RANSAC always uses one thread, so the "
        "result does not depend on it (KISS-Matcher schedules its own)",
    )
    parser.add_argument(
        "--fallback",
        help="method run when the result's fitness is below --min-fitness (e.g. ransac+icp after dvds+icp on partial "
        "scans); the result with the higher fitness is kept",
    )
    parser.add_argument(
        "--min-fitness",
        type=float,
        help="fitness below which a result counts as failed (default: 0.5 for learned methods, which then warn "
        "unless --fallback is given; no check for classical methods)",
    )
    parser.add_argument(
        "--ransac-iterations",
        type=int,
        help="RANSAC's iteration limit in every step that runs it (default: 100,000; 25,000 in the default's fallback)",
    )
    parser.add_argument("--out", help="write the 4x4 transform: .txt, .json (with diagnostics) or .npy")
    parser.add_argument("--save-aligned", help="write the moved source as a .ply")
    parser.add_argument("--plot", help="write a before/after picture (.png, three orthogonal views)")
    parser.add_argument("--plot-dpi", type=int, default=120, help="resolution of --plot (default: %(default)s)")
    parser.add_argument("--show", action="store_true", help="open an Open3D window with the aligned clouds")
    many = parser.add_argument_group("many pairs (--pairs)")
    many.add_argument("--results", help="results CSV (default: register_results.csv in the current folder)")
    many.add_argument("--resume", action="store_true", help="keep the rows of an existing results CSV, run the rest")
    many.add_argument(
        "--rre",
        type=float,
        help="recall threshold on the rotation error, degrees (default: the dataset's: 3DMatch 15, KITTI 5, CSV 5)",
    )
    many.add_argument(
        "--rte",
        type=float,
        help="recall threshold on the translation error, cloud units (default: "
        "3DMatch 0.3, KITTI 2.0, CSV none: set it)",
    )
    many.add_argument(
        "--rmse",
        type=float,
        default=0.2,
        help="3DMatch recall: RMSE of the ground-truth correspondences (gt.info) below this (default: %(default)s m)",
    )
    many.add_argument("--limit", type=int, help="register only the first N pairs")
    many.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


class _Usage(Exception):
    """An argument mistake (exit code 2)."""


def _check_args(args: argparse.Namespace) -> None:
    if args.pairs is None and (args.src is None or args.ref is None):
        raise _Usage("give SRC and REF files, or --pairs FILE")
    if args.pairs is not None and (args.src is not None or args.save_aligned or args.plot or args.show or args.init):
        raise _Usage(
            "--pairs registers the pairs of its file: SRC/REF, --init, --save-aligned, --plot and --show "
            "apply to one pair"
        )
    if args.out is not None:
        check_suffix(args.out, TRANSFORM_SUFFIXES, "--out")
    if args.save_aligned is not None:
        check_suffix(args.save_aligned, (".ply",), "--save-aligned")
    if args.plot is not None:
        check_suffix(args.plot, (".png",), "--plot")
    if args.show:
        from lcreg.viz import check_display

        check_display()  # before the work: no window can open here
    for option in ("out", "save_aligned", "plot", "results"):
        value = getattr(args, option)
        if value is not None and not Path(value).expanduser().parent.is_dir():
            raise _Usage(f"--{option.replace('_', '-')} {value!r}: folder {str(Path(value).parent)!r} does not exist")


def _print_result(result: Registration) -> None:
    np.set_printoptions(suppress=True, precision=6, linewidth=120)
    print(f"source:    {result.sources[0]} ({result.num_points[0]} points)")
    print(f"reference: {result.sources[1]} ({result.num_points[1]} points)")
    print(
        f"method:    {result.method}, voxel size {result.voxel_size:.6g} (clouds' unit), "
        f"{result.used_points[0]} + {result.used_points[1]} points used"
    )
    if "fallback" in result.extra:
        f = result.extra["fallback"]
        why = (
            "found no solution" if f.get("no_solution") else f"fitness {f['first_fitness']:.3f} < {f['min_fitness']:g}"
        )
        print(f"fallback:  {f['first']} {why}: ran {f['ran']} (fitness {f['ran_fitness']:.3f}), kept {f['kept']}")
    print("transform (maps source points into the reference frame):")
    for row in result.transform:
        print("  " + "  ".join(f"{x: .6f}" for x in row))
    gate = 2 * result.voxel_size
    print(f"fitness:   {result.fitness:.4f} (share of source points within {gate:.4g} of the reference)")
    print(f"inlier RMSE: {result.inlier_rmse:.6g}")
    print(f"time:      {result.time_s * 1000:.0f} ms")


def _one_pair(args: argparse.Namespace) -> None:
    init = None if args.init is None else read_transform(args.init)
    result = register(
        args.src,
        args.ref,
        args.method,
        weights=args.weights,
        refine=args.refine,
        voxel_size=args.voxel_size,
        init=init,
        target_points=args.target_points,
        seed=args.seed,
        fallback=args.fallback,
        min_fitness=args.min_fitness,
        threads=args.threads,
        ransac_iterations=args.ransac_iterations,
    )
    _print_result(result)
    if args.out:
        print(f"wrote {write_transform(args.out, result.transform, result.to_dict())}")
    if args.save_aligned or args.plot or args.show:
        from lcreg.registration.inputs import as_cloud

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the NaN rows were reported above
            src, ref = as_cloud(args.src, "points_src").points, as_cloud(args.ref, "points_ref").points
        if args.save_aligned:
            print(f"wrote {write_ply(args.save_aligned, result.apply(src))}")
        if args.plot:
            from lcreg.viz import plot_registration

            title = f"{Path(args.src).name} -> {Path(args.ref).name}: {result.method}, fitness {result.fitness:.3f}"
            plot_registration(src, ref, result.transform, args.plot, title=title, dpi=args.plot_dpi)
            print(f"wrote {args.plot}")
        if args.show:
            from lcreg.viz import show_registration

            show_registration(src, ref, result.transform)


def _one_line(message: Warning | str, category: type[Warning], *args: object, **kwargs: object) -> str:
    """``warnings.formatwarning`` of the command: ``lcreg register: warning: <message>`` (no source line)."""
    return f"lcreg register: warning: {message}\n"


def run(argv: Sequence[str]) -> None:
    """Parse ``argv`` and run (errors raise; :func:`main` turns them into exit codes).

    Warnings (NaN rows dropped, pairs skipped) print as one line each; recording them (pytest) is unaffected.
    """
    previous = warnings.formatwarning
    warnings.formatwarning = _one_line
    try:
        _run(argv)
    finally:
        warnings.formatwarning = previous


def _run(argv: Sequence[str]) -> None:
    args = build_parser().parse_args(list(argv))
    _check_args(args)
    if args.pairs is not None:
        from lcreg.registration.many import run_pairs

        run_pairs(args)
    else:
        _one_pair(args)


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point of ``lcreg register`` (exit code 2 for arguments, 1 for files, clouds and weights)."""
    argv = sys.argv[1:] if argv is None else argv
    if os.environ.get("LCREG_DEBUG", "") not in ("", "0"):
        run(argv)
        return
    try:
        run(argv)
    except _Usage as err:
        _fail(str(err), 2)
    except MethodError as err:
        _fail(str(err), 2)
    except Exception as err:
        if not isinstance(err, _user_errors()):
            raise  # a bug: keep the traceback
        _fail(str(err), 1)


def _user_errors() -> tuple[type[Exception], ...]:
    """Errors about the user's files, clouds, weights or display (one line, exit code 1)."""
    from lcreg.checkpoints import CheckpointError  # the root of the weights and checkpoint errors

    errors: tuple[type[Exception], ...] = (OSError, ValueError, CheckpointError, MissingDependencyError)
    try:
        from lcreg.viz import DisplayUnavailableError
    except ImportError:  # pragma: no cover
        return errors
    return (*errors, DisplayUnavailableError)


def _fail(message: str, code: int) -> NoReturn:
    from lcreg.checkpoints import one_line

    sys.stderr.write(f"lcreg register: error: {one_line(message, 1000)}\n")
    sys.stderr.write("hint: `lcreg register --help` lists the options and methods; LCREG_DEBUG=1 shows the traceback\n")
    raise SystemExit(code)
