"""``casadi-design plot``: redraw the figures of a results file, without solving."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import OutputError
from ..records.files import read_results
from . import common

HELP = "redraw the figures and viewer.html from results.json or sweep.json"
DESCRIPTION = ("Redraw fig1 (error bands along the test poses, mm) and, for a sweep, sweep_max_error "
               "(max error in mm vs m) from a results file, without solving; and viewer.html (every plan "
               "in its cell, one pose at a time) from the results' problem file.")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("plot", help=HELP, description=DESCRIPTION)
    p.add_argument("results", help="results.json, sweep.json, or the folder holding one")
    p.add_argument("--out", metavar="DIR", help="folder for the figures (default: the results' folder)")
    p.add_argument("--m", type=common.m_values, metavar="LIST",
                   help="m of the fig1 panels, e.g. 1,5 (default: the first and last m)")
    p.add_argument("--log", action="store_true", help="logarithmic axes in sweep_max_error")
    p.add_argument("--format", type=common.formats, default=["png", "pdf"], metavar="LIST",
                   help="file formats, comma separated: png, pdf, svg (default: png,pdf)")
    p.add_argument("--force", action="store_true", help="overwrite figures that exist")
    common.add_common(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ..reports.plotting import fig1, save_figures, sweep_figure
    from ..records.results import design_from_record
    from ..execution.sweep import sweep_from_record

    if args.out is not None and not args.out.strip():
        raise OutputError("--out is empty; give a folder name (or leave --out out to write beside the results)")
    record = read_results(Path(args.results))
    src = Path(record["_path"])
    out = Path(args.out) if args.out is not None else src.parent
    designs = [design_from_record(d) for d in record["designs"]]
    available = sorted({d.m for d in designs})
    figures = {"fig1": fig1(np.array([t["position_m"] for t in record["test_poses"]]), designs,
                            common.fig_m(args.m, available, (), "--m"))}
    if "sweep" in record:
        figures["sweep_max_error"] = sweep_figure(sweep_from_record(record), args.log)
    from ..reports.viewer import VIEWER_NAME, results_problem, write_viewer

    problem, why = results_problem(record)  # viewer.html needs the robot and its cell
    targets = [out / f"{stem}.{fmt}" for stem in figures for fmt in args.format]
    targets += [out / VIEWER_NAME] if problem is not None else []
    existing = [t for t in targets if t.exists()]
    if existing and not args.force:
        raise OutputError(f"{existing[0]}: exists; add --force to overwrite it (or choose another --out)")
    for stem, fig in figures.items():
        save_figures(fig, [out / f"{stem}.{fmt}" for fmt in args.format])
    if problem is not None:
        write_viewer(out, problem, designs)
    common.say(args, "wrote " + ", ".join(str(t) for t in targets)
               + ("" if problem is not None else f"; no {VIEWER_NAME}: {why}"))
    return 0
