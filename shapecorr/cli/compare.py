"""``compare.py``: compare runs from their output folders; also what ends every multirun (docs/compare.md).

    python compare.py OUT1 OUT2 ... [--names a b ...] [--out DIR] [--allow-different-pairs] [--n-examples 4]
        [--data-root DIR]

Writes into ``--out`` (default: the current folder's ``comparison/``): ``comparison.csv``, ``comparison.md``,
``pck_overlay.png``, ``mean_error.png``, ``pairwise.png`` (two runs: scatter; more: win/loss matrix),
``examples_grid.png``, ``interp_overlay.png`` (several interpolating runs) and ``report.html``. Runs on
different datasets or pair sets are refused (``error: ...``, exit status 2) unless ``--allow-different-pairs``,
which compares on the common pairs and says how many. Training runs (``train.py``) give table rows only.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

from shapecorr.cli.common import exit_on_user_error
from shapecorr.eval import compare
from shapecorr.viz import compare as figures
from shapecorr.viz.render import DEFAULT_VIEW
from shapecorr.viz.report_html import REPORT_HTML, write_report_html

DEFAULT_OUT = "comparison"
DEFAULT_EXAMPLES = 4
#: Titles of the figures embedded in report.html, by file name (in page order).
FIGURE_TITLES = {
    figures.PCK_OVERLAY_PNG: "Cumulative error curves (PCK)",
    figures.MEAN_ERROR_PNG: "Mean error (published numbers dashed)",
    figures.PAIRWISE_PNG: "Per pair",
    figures.INTERP_OVERLAY_PNG: "Interpolation",
    figures.EXAMPLES_GRID_PNG: "Example pairs",
}


def write_comparison(paths: Sequence[str | Path], out_dir: str | Path, names: Sequence[str] | None = None,
                     allow_different_pairs: bool = False, n_examples: int = DEFAULT_EXAMPLES,
                     view=DEFAULT_VIEW, data_root: str | Path | None = None) -> Path:
    """Compare the run folders ``paths`` and write every output into ``out_dir``; returns ``comparison.md``.

    The example meshes are read from ``data_root``, by default the runs' data folder (``run.json``).

    Raises
    ------
    ShapeCorrError
        Unreadable or incomparable runs (:class:`~shapecorr.eval.compare.ComparisonError`), missing meshes.
    """
    out = Path(out_dir)
    runs, pairs, note = compare.compare_runs(paths, names, allow_different_pairs)
    if note:
        print(note, file=sys.stderr)
    out.mkdir(parents=True, exist_ok=True)
    compare.write_text(out / compare.COMPARISON_CSV, compare.comparison_csv(runs))
    md = compare.write_text(out / compare.COMPARISON_MD, compare.comparison_markdown(runs, note))
    examples = figures.example_pairs(pairs, n_examples)
    data_roots = {r.dataset for r in runs if r.has_records and r.dataset} if data_root is None else {data_root}
    meshes = {}
    if examples and len(data_roots) == 1:
        meshes = figures.load_meshes(data_roots.pop(), [s for pair in examples for s in pair])
    _, published = compare.published_rows(runs)
    written = figures.write_figures(out, runs, pairs, examples, meshes, view, published)
    embedded = {FIGURE_TITLES[k]: written[k] for k in FIGURE_TITLES if k in written}
    write_report_html(out / REPORT_HTML, runs, embedded, examples, meshes, note)
    return md


def compare_sweep(sweep_dir: str | Path) -> Path | None:
    """Compare the runs of a Hydra sweep folder into that folder (None when fewer than two runs finished)."""
    runs = compare.find_sweep_runs(sweep_dir)
    if len(runs) < 2:
        return None
    return write_comparison(runs, sweep_dir)


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The command line of ``compare.py`` (see the module docstring)."""
    parser = argparse.ArgumentParser(prog="compare.py", description="Compare evaluate.py / train.py output folders "
                                     "(docs/compare.md).")
    parser.add_argument("runs", nargs="+", help="output folders (or one Hydra sweep folder holding them)")
    parser.add_argument("--names", nargs="+", help="a display name per folder (default: their distinguishing options)")
    parser.add_argument("--out", default=DEFAULT_OUT, help=f"output folder (default: ./{DEFAULT_OUT})")
    parser.add_argument("--allow-different-pairs", action="store_true",
                        help="compare runs on different pair sets on their common pairs")
    parser.add_argument("--n-examples", type=int, default=DEFAULT_EXAMPLES,
                        help="example pairs shown per run (grid and 3-D views; 0: none)")
    parser.add_argument("--data-root", help="where the example meshes are (default: the runs' data folder, "
                        "run.json's data_root; for runs made on another machine)")
    return parser.parse_args(argv)


@exit_on_user_error
def main(argv: Sequence[str] | None = None) -> int:
    """Run ``compare.py``; returns 0 (errors exit with status 2 through :func:`exit_on_user_error`)."""
    args = parse_args(argv)
    paths = [Path(p) for p in args.runs]
    if len(paths) == 1 and not (paths[0] / compare.METRICS_FILE).is_file():
        paths = compare.find_sweep_runs(paths[0])  # a sweep folder: its runs
    if len(paths) < 2:
        raise compare.ComparisonError(f"{len(paths)} run folder(s) to compare; give at least two")
    md = write_comparison(paths, args.out, args.names, args.allow_different_pairs, args.n_examples,
                          data_root=args.data_root)
    print(md.read_text(), end="")
    print(f"comparison written to {md.parent}", flush=True)
    return 0

