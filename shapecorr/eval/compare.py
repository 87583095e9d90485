"""Compare evaluation runs read from their output folders (docs/compare.md).

A *run* is a folder written by ``evaluate.py`` (``metrics.json``, ``per_pair.csv``, ``run.json``,
``pairs/<x>__<y>.json/.npz``, ``maps/``, ``interp/``; docs/evaluation.md §6) or by ``train.py`` (``metrics.json``
with the test metrics only). Everything here reads those files, never how they were computed, so any two
folders can be compared. Drawing is :mod:`shapecorr.viz.compare`'s.

Rules:

* runs on different datasets, splits or pair sets are refused (:class:`ComparisonError` naming the difference)
  unless ``allow_different_pairs``; the comparison is then restricted to the pairs common to all runs and every
  number is recomputed on them from the per-pair records;
* a run's name is given, or made of the options that distinguish it from the other runs (its Hydra overrides in
  ``.hydra/overrides.yaml`` when there are any, else the matcher and post-processing of ``run.json``);
* published numbers (:data:`PUBLISHED`) are separate reference rows, never ranked with measured rows.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from shapecorr.data.cache import atomic_open
from shapecorr.errors import ShapeCorrError
from shapecorr.eval import reports
from shapecorr.eval.records import load_record

METRICS_FILE = "metrics.json"
PER_PAIR_FILE = "per_pair.csv"
RUN_FILE = "run.json"
OVERRIDES_FILE = Path(".hydra") / "overrides.yaml"
COMPARISON_CSV = "comparison.csv"
COMPARISON_MD = "comparison.md"

#: Options of a run that never distinguish methods (the same for every run of a sweep, or bookkeeping).
IGNORED_OVERRIDES = ("progress", "output_dir", "hydra.", "resume", "workers", "n_examples", "start_method")


class ComparisonError(ShapeCorrError):
    """Runs that cannot be compared: a folder without results, or runs on different data or pairs."""


@dataclass(frozen=True)
class Column:
    """A column of the comparison table.

    Attributes
    ----------
    key : str
        Key in :class:`Run` ``.values`` (and the CSV header).
    title : str
        Header of ``comparison.md`` / ``report.html``.
    better : str
        ``"lower"``, ``"higher"`` or ``""`` (not ranked).
    scale : float
        Display factor (100 for errors: papers print x100).
    digits : int
        Decimals shown.
    """

    key: str
    title: str
    better: str = "lower"
    scale: float = 1.0
    digits: int = 3


#: The columns of comparison.csv / .md, in order (absent values stay empty).
COLUMNS = (
    Column("mean_geodesic_error", "mean error (x100)", "lower", 100.0, 2),
    Column("median_geodesic_error", "median error (x100)", "lower", 100.0, 2),
    Column("pck_auc", "PCK AUC", "higher", 1.0, 3),
    Column("mean_geodesic_error_sym", "vs mirrored GT (x100)", "", 100.0, 2),
    Column("mean_initial_geodesic_error", "before post-processing (x100)", "lower", 100.0, 2),
    Column("mean_conformal_distortion", "conformal distortion of the map", "lower", 1.0, 3),
    Column("mean_deformation_conformal_distortion", "interp. conformal distortion", "lower", 1.0, 4),
    Column("mean_chamfer", "interp. Chamfer at t=1", "lower", 1.0, 4),
    Column("mean_volume_score", "interp. volume score at t=1", "lower", 1.0, 4),
    Column("seconds_per_pair", "s / pair", "lower", 1.0, 2),
    Column("peak_memory_mb", "peak memory (MB)", "lower", 1.0, 0),
)

#: Published mean geodesic errors (x100 as printed, fractions here) per benchmark, as recorded in the docs
#: (docs/compare.md §4 lists them): (method, mean error as a fraction, source).
PUBLISHED: dict[str, tuple[tuple[str, float, str], ...]] = {
    "faust_r": (
        ("Deep Shells", 0.017, "Eisenberger et al., NeurIPS 2020 (docs/deep_shells.md)"),
        ("Smooth Shells", 0.025, "Eisenberger et al., CVPR 2020 (docs/smooth_shells.md)"),
        ("NeuroMorph", 0.023, "Eisenberger et al., CVPR 2021 (docs/neuromorph.md)"),
        ("NeuroMorph + Smooth Shells", 0.015, "Eisenberger et al., CVPR 2021 (docs/smooth_shells.md)"),
        ("G-MSM", 0.015, "Eisenberger et al., CVPR 2023 (docs/gmsm.md)"),
    ),
}


@dataclass
class Run:
    """One run read from its folder.

    Attributes
    ----------
    path : Path
    name : str
        Display name (given, or from the distinguishing options; see :func:`name_runs`).
    metrics : dict
        ``metrics.json`` as written.
    info : dict
        ``run.json`` (empty for training runs), with ``metrics["run"]``'s extra keys (device, date, ...).
    overrides : list of str
        Hydra overrides of the run (``.hydra/overrides.yaml``), empty when absent.
    pairs : list of (str, str)
        The evaluated pairs in ``per_pair.csv`` order (empty for training runs).
    values : dict
        The row of the comparison: the :data:`COLUMNS` keys, ``n_pairs``, ``device``, and for evaluation runs
        ``pck`` / ``interp_curves`` (recomputed on the compared pairs).
    """

    path: Path
    name: str
    metrics: dict[str, Any]
    info: dict[str, Any]
    overrides: list[str] = field(default_factory=list)
    pairs: list[tuple[str, str]] = field(default_factory=list)
    values: dict[str, Any] = field(default_factory=dict)

    @property
    def has_records(self) -> bool:
        """Whether per-pair records exist (an ``evaluate.py`` run), i.e. per-pair comparisons are possible."""
        return bool(self.pairs)

    @property
    def dataset(self) -> str:
        """The data folder of the run (``run.json``'s ``data_root``), or ``""`` when unknown."""
        return str(self.info.get("data_root") or "")


def _read_json(path: Path) -> dict[str, Any]:
    try:
        value = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise ComparisonError(f"unreadable ({err})", path) from None
    if not isinstance(value, dict):
        raise ComparisonError("expected a JSON object", path)
    return value


def _read_overrides(path: Path) -> list[str]:
    """The overrides list Hydra writes (``- key=value`` lines), without a YAML dependency."""
    if not path.is_file():
        return []
    lines = [line.strip() for line in path.read_text().splitlines()]
    return [line[2:].strip().strip("'\"") for line in lines if line.startswith("- ")]


def _read_pairs(path: Path) -> list[tuple[str, str]]:
    with open(path, newline="", encoding="utf-8", errors="surrogateescape") as fh:
        reader = csv.DictReader(fh)
        if reader.fieldnames is None or not {"source", "target"} <= set(reader.fieldnames):
            raise ComparisonError("no source/target columns", path)
        return [(row["source"], row["target"]) for row in reader]


def load_run(path: str | os.PathLike, name: str | None = None) -> Run:
    """Read a run folder (``metrics.json`` required; ``per_pair.csv``, ``run.json``, overrides when present).

    Raises
    ------
    ComparisonError
        The folder does not exist or has no ``metrics.json`` (unfinished or not an output folder).
    """
    path = Path(path)
    if not path.is_dir():
        raise ComparisonError("not a folder", path)
    metrics_path = path / METRICS_FILE
    if not metrics_path.is_file():
        raise ComparisonError(f"no {METRICS_FILE}: not a finished evaluate.py / train.py output folder", path)
    metrics = _read_json(metrics_path)
    info = _read_json(path / RUN_FILE) if (path / RUN_FILE).is_file() else {}
    info = {**(metrics.get("run") or {}), **info}
    pairs = _read_pairs(path / PER_PAIR_FILE) if (path / PER_PAIR_FILE).is_file() else []
    return Run(path=path, name=name or "", metrics=metrics, info=info,
               overrides=_read_overrides(path / OVERRIDES_FILE), pairs=pairs)


def _short(target: str | None) -> str:
    return "" if not target else str(target).rsplit(".", 1)[-1]


def _describe(run: Run) -> str:
    """A name from ``run.json``: matcher class, + post-processing, + checkpoint or maps folder."""
    info = run.info
    text = _short(info.get("matcher")) or run.path.name
    post = info.get("postprocess")
    if isinstance(post, dict) and post.get("_target_"):
        text += f" + {_short(post['_target_'])}"
    interp = info.get("interpolator")
    if isinstance(interp, dict) and interp.get("_target_"):
        text += f" ({_short(interp['_target_'])})"
    for key in ("ckpt_path", "maps_dir"):
        if info.get(key):
            text += f" [{Path(str(info[key])).name}]"
    return text


def _distinguishing(overrides: Sequence[list[str]]) -> list[list[str]]:
    """Per run, its overrides that are not shared by every run (and are not bookkeeping options)."""
    kept = [[o for o in ovs if not o.lstrip("+~").startswith(IGNORED_OVERRIDES)] for ovs in overrides]
    common = set.intersection(*(set(k) for k in kept)) if len(kept) > 1 else set()
    return [[o for o in k if o not in common] for k in kept]


def name_runs(runs: Sequence[Run], names: Sequence[str] | None = None) -> None:
    """Set every run's ``name``: the given names, else distinguishing overrides, else :func:`_describe`.

    Names are made unique by appending the folder name where two coincide.

    Raises
    ------
    ComparisonError
        ``names`` given with a different length than ``runs``.
    """
    if names:
        if len(names) != len(runs):
            raise ComparisonError(f"{len(names)} names for {len(runs)} runs (--names gives one per folder)")
        for run, name in zip(runs, names):
            run.name = str(name)
        return
    options = _distinguishing([r.overrides for r in runs])
    for run, opts in zip(runs, options):
        short = [o.lstrip("+").split("=", 1)[-1] if o.lstrip("+").startswith(("method=", "model=")) else o
                 for o in opts]
        run.name = " ".join(short) if short and all(options) else _describe(run)
    seen: dict[str, int] = {}
    for run in runs:
        seen[run.name] = seen.get(run.name, 0) + 1
    for run in runs:
        if seen[run.name] > 1:
            run.name = f"{run.name} ({run.path.name})"


def common_pairs(runs: Sequence[Run], allow_different_pairs: bool = False) -> tuple[list[tuple[str, str]], str]:
    """The pairs all runs are compared on, and a one-line note (empty when every run has the same pairs).

    Raises
    ------
    ComparisonError
        Different datasets / splits, or different pair sets without ``allow_different_pairs`` (the message
        names the runs and the difference), or no pair in common.
    """
    with_pairs = [r for r in runs if r.has_records]
    if not with_pairs:
        return [], ""
    for key, what in (("data_root", "datasets"), ("split", "splits")):
        seen = {str(r.info.get(key)) for r in with_pairs if r.info.get(key) is not None}
        if len(seen) > 1:
            described = "; ".join(f"{r.path}: {r.info.get(key)}" for r in with_pairs)
            raise ComparisonError(f"the runs are on different {what} ({described})")
    reference = with_pairs[0]
    ref_set = set(reference.pairs)
    differing = [r for r in with_pairs[1:] if set(r.pairs) != ref_set]
    if not differing:
        return list(reference.pairs), ""
    common = [p for p in reference.pairs if all(p in set(r.pairs) for r in with_pairs)]
    if not allow_different_pairs:
        r = differing[0]
        only_a, only_b = sorted(ref_set - set(r.pairs)), sorted(set(r.pairs) - ref_set)
        where, example = ("first", only_a[0]) if only_a else ("second", only_b[0])
        raise ComparisonError(
            f"different pairs: {reference.path} has {len(reference.pairs)}, {r.path} has {len(r.pairs)} "
            f"({len(only_a)} only in the first, {len(only_b)} only in the second, e.g. {example[0]} -> {example[1]} "
            f"only in the {where}); "
            f"{len(common)} in common over all runs: pass --allow-different-pairs to compare on those")
    if not common:
        raise ComparisonError("the runs have no pair in common")
    return common, f"compared on the {len(common)} pairs common to all {len(with_pairs)} runs"


def _row_values(run: Run, pairs: Sequence[tuple[str, str]]) -> dict[str, Any]:
    """Metrics of ``run`` on ``pairs``: recomputed from the per-pair records when the pair set is smaller."""
    m = run.metrics
    if run.has_records and len(pairs) != len(run.pairs):
        loaded = [load_record(run.path, x, y) for x, y in pairs]
        m = {**m, **reports.aggregate([r for r, _, _ in loaded], [e for _, e, _ in loaded],
                                      [s for _, _, s in loaded])}
    values: dict[str, Any] = {c.key: m.get(c.key) for c in COLUMNS}
    values["n_pairs"] = m.get("n_pairs") if run.has_records else m.get("n_pairs", m.get("test_pairs"))
    values["device"] = str(run.info.get("device") or "")
    values["pck"] = m.get("pck")
    values[reports.CURVES_KEY] = m.get(reports.CURVES_KEY)
    return values


def compare_runs(
    paths: Sequence[str | os.PathLike],
    names: Sequence[str] | None = None,
    allow_different_pairs: bool = False,
) -> tuple[list[Run], list[tuple[str, str]], str]:
    """Load and check the runs, name them and compute their rows on the common pairs.

    Returns
    -------
    runs : list of Run
        With ``name`` and ``values`` set.
    pairs : list of (str, str)
        The compared pairs (empty when no run has per-pair records).
    note : str
        How many pairs were compared when the pair sets differ, else ``""``.
    """
    if not paths:
        raise ComparisonError("no run folder given")
    runs = [load_run(p) for p in paths]
    name_runs(runs, names)
    pairs, note = common_pairs(runs, allow_different_pairs)
    for run in runs:
        run.values = _row_values(run, pairs)
    return runs, pairs, note


def per_pair_errors(runs: Sequence[Run], pairs: Sequence[tuple[str, str]]) -> np.ndarray:
    """Per-pair mean errors ``(n_runs, n_pairs)`` float64 read from each run's ``per_pair.csv``."""
    out = np.full((len(runs), len(pairs)), np.nan)
    index = {p: k for k, p in enumerate(pairs)}
    for i, run in enumerate(runs):
        with open(run.path / PER_PAIR_FILE, newline="", encoding="utf-8", errors="surrogateescape") as fh:
            for row in csv.DictReader(fh):
                k = index.get((row["source"], row["target"]))
                if k is not None:
                    out[i, k] = float(row["mean_error"])
    return out


def win_matrix(errors: np.ndarray) -> np.ndarray:
    """``(r, r)`` int: entry (a, b) = number of pairs where run a's error is strictly below run b's.

    Parameters
    ----------
    errors : (r, p) float
        Per-pair errors (:func:`per_pair_errors`).
    """
    return (errors[:, None, :] < errors[None, :, :]).sum(axis=2)


def published_rows(runs: Sequence[Run]) -> tuple[str, tuple[tuple[str, float, str], ...]]:
    """``(benchmark, rows)`` of :data:`PUBLISHED` when every run's data folder is that benchmark, else ``("", ())``.

    A data folder is recognised by its name (``.../FAUST_r``; case-insensitive).
    """
    names = {Path(r.dataset).name.lower() for r in runs if r.dataset}
    if len(names) == 1:
        name = names.pop()
        if name in PUBLISHED:
            return Path(next(r.dataset for r in runs if r.dataset)).name, PUBLISHED[name]
    return "", ()


def best_runs(runs: Sequence[Run]) -> dict[str, set[int]]:
    """Per ranked column, the indices of the runs holding the best value (ties all marked)."""
    best: dict[str, set[int]] = {}
    for c in COLUMNS:
        if not c.better:
            continue
        vals = [(i, r.values.get(c.key)) for i, r in enumerate(runs)]
        vals = [(i, float(v)) for i, v in vals if v is not None and math.isfinite(float(v))]
        if len(vals) < 2:
            continue
        target = min(v for _, v in vals) if c.better == "lower" else max(v for _, v in vals)
        best[c.key] = {i for i, v in vals if math.isclose(v, target, rel_tol=1e-12, abs_tol=0.0)}
    return best


def shown_columns(runs: Sequence[Run]) -> list[Column]:
    """The columns at least one run has a value for."""
    return [c for c in COLUMNS if any(r.values.get(c.key) is not None for r in runs)]


def format_value(column: Column, value: Any) -> str:
    """A cell: ``value * scale`` with the column's decimals, ``""`` when absent."""
    if value is None:
        return ""
    return f"{float(value) * column.scale:.{column.digits}f}"


def comparison_csv(runs: Sequence[Run]) -> str:
    """``comparison.csv``: one row per run, raw values (errors as fractions), ``best_in`` listing its best columns."""
    best = best_runs(runs)
    text = io.StringIO()
    header = ["name", "folder", "dataset", "n_pairs", *[c.key for c in COLUMNS], "device", "best_in"]
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(header)
    for i, r in enumerate(runs):
        writer.writerow([r.name, str(r.path), r.dataset, r.values.get("n_pairs"),
                         *["" if r.values.get(c.key) is None else r.values[c.key] for c in COLUMNS],
                         r.values.get("device", ""), " ".join(k for k, s in best.items() if i in s)])
    return text.getvalue()


def comparison_markdown(runs: Sequence[Run], note: str = "") -> str:
    """``comparison.md``: the measured table (best per column in bold), then the published rows, if any."""
    cols = shown_columns(runs)
    best = best_runs(runs)
    dataset = ", ".join(sorted({Path(r.dataset).name for r in runs if r.dataset})) or "unknown data"
    lines = [f"# Comparison: {len(runs)} runs on {dataset}", ""]
    if note:
        lines += [note, ""]
    lines += ["| run | pairs | " + " | ".join(c.title for c in cols) + " | device |",
              "|---|---|" + "---|" * len(cols) + "---|"]
    for i, r in enumerate(runs):
        cells = []
        for c in cols:
            cell = format_value(c, r.values.get(c.key))
            cells.append(f"**{cell}**" if cell and i in best.get(c.key, ()) else cell)
        lines.append(f"| {r.name} | {r.values.get('n_pairs') or ''} | " + " | ".join(cells)
                     + f" | {r.values.get('device', '')} |")
    lines += ["", "Bold: best measured value per column. Errors are geodesic, x100 of sqrt(area) "
              "(docs/evaluation.md). Folders:", ""]
    lines += [f"- {r.name}: `{r.path}`" for r in runs]
    bench, rows = published_rows(runs)
    if rows:
        lines += ["", f"## Published (papers' numbers on all {bench} test pairs; not measured here)", "",
                  "| method | mean error (x100) | source |", "|---|---|---|"]
        lines += [f"| {m} (published) | {100 * v:.1f} | {src} |" for m, v, src in rows]
    return "\n".join(lines) + "\n"


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_open(path) as fh:
        fh.write(text.encode("utf-8", "surrogateescape"))
    return path


def find_sweep_runs(sweep_dir: str | os.PathLike) -> list[Path]:
    """The run folders of a Hydra sweep folder: its subfolders holding ``metrics.json``, in job-number order."""
    sweep_dir = Path(sweep_dir)
    if not sweep_dir.is_dir():
        raise ComparisonError("sweep folder does not exist", sweep_dir)
    found = [p for p in sweep_dir.iterdir() if p.is_dir() and (p / METRICS_FILE).is_file()]
    return sorted(found, key=lambda p: (0, int(p.name), "") if p.name.isdigit() else (1, 0, p.name))
