"""Generate the procedural creature dataset (FAUST_r-style folder with dense ground truth).

Usage::

    python data_prep/make_synthetic.py out=DIR [preset=default|tiny|large] [seed=0] [workers=N]
                                       [preview=PNG] [OPTION=VALUE ...]

Every ``OPTION`` of :class:`shapecorr.data.synthetic.SyntheticConfig` can be set (``--help`` lists them
with their defaults); a preset supplies the defaults that the options then override. The folder is
written atomically (a temporary folder renamed into place) and left untouched when it already holds a
dataset generated with exactly the same options. ``preview=PNG`` additionally renders a few shapes.
Exit status 2 with a one-line message on invalid options or an unusable output folder.
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from dataclasses import fields
from pathlib import Path

import numpy as np

from shapecorr.data.synthetic import PRESETS, SyntheticConfig, ensure_synthetic_dataset, preset
from shapecorr.errors import ConfigError, ShapeCorrError

#: Options of the script itself (not dataset options).
SCRIPT_OPTIONS = {
    "out": "output folder (required)",
    "preset": f"defaults to start from: {', '.join(sorted(PRESETS))} (default: default)",
    "workers": "worker processes (default: available cores, at most 8); does not change the files",
    "preview": "also render a few generated shapes into this PNG file",
    "progress": "show a progress bar (default: true)",
}
#: Shapes shown by ``preview=``: pose index of a few subjects of each class.
PREVIEW_SHAPES = (("human", 0, 0), ("human", 1, 2), ("human", 2, 5), ("human", 3, 7), ("human", 4, 8),
                  ("quad", 0, 1), ("quad", 1, 3), ("quad", 2, 4))
#: Rotation from the files' axes (y up) to matplotlib's (z up).
_PLOT_AXES = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
#: Camera azimuth (degrees) of the preview per class: humans from the front-left, quadrupeds from the side.
PREVIEW_AZIMUTH = {"human": -65.0, "quad": -20.0}
_TRUE = {"1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off"}


def option_docs() -> dict[str, str]:
    """Per-option descriptions, read from the numpy-style ``Attributes`` section of SyntheticConfig."""
    doc = SyntheticConfig.__doc__ or ""
    section = doc.split("Attributes", 1)[-1]
    out: dict[str, str] = {}
    current: list[str] = []
    for line in section.splitlines()[2:]:
        if re.match(r"^    [a-z_]", line):
            current = [name.strip() for name in line.strip().split(",")]
            for name in current:
                out[name] = ""
        elif line.strip() and current:
            for name in current:
                out[name] = (out[name] + " " + line.strip()).strip()
    return out


def _help_text() -> str:
    defaults = SyntheticConfig()
    docs = option_docs()
    lines = [__doc__.strip(), "", "Script options:"]
    lines += [f"  {name}=...  {text}" for name, text in SCRIPT_OPTIONS.items()]
    lines += ["", "Dataset options (default preset values; see also the presets below):"]
    for f in fields(SyntheticConfig):
        lines.append(f"  {f.name}={getattr(defaults, f.name)!r}  {docs.get(f.name, '')}")
    lines += ["", "Presets (overrides of the defaults):"]
    lines += [f"  {name}: {values or '(the defaults)'}" for name, values in PRESETS.items()]
    return "\n".join(lines)


def _convert(name: str, text: str, kind) -> object:
    try:
        if kind in (bool, "bool"):
            low = text.lower()
            if low not in _TRUE | _FALSE:
                raise ValueError
            return low in _TRUE
        if kind in (int, "int"):
            return int(text)
        if kind in (float, "float"):
            return float(text)
        return text
    except ValueError:
        expected = getattr(kind, "__name__", kind)
        raise ConfigError(f"option {name}={text!r}: expected a value of type {expected}") from None


def parse_options(tokens: list[str]) -> tuple[dict, SyntheticConfig]:
    """Split ``key=value`` tokens into script options and a :class:`SyntheticConfig`.

    Raises
    ------
    ConfigError
        A token without ``=``, an unknown key, a value of the wrong type, or a missing ``out``.
    """
    kinds = {f.name: f.type for f in fields(SyntheticConfig)}
    script: dict = {"preset": "default", "workers": None, "preview": None, "progress": True}
    overrides: dict = {}
    for token in tokens:
        if "=" not in token:
            raise ConfigError(f"expected key=value, got {token!r} (see --help)")
        key, value = token.split("=", 1)
        key = key.strip().lstrip("+")
        if key in SCRIPT_OPTIONS:
            if key == "workers":
                script[key] = _convert(key, value, int)
            elif key == "progress":
                script[key] = _convert(key, value, bool)
            else:
                script[key] = value
        elif key in kinds:
            overrides[key] = _convert(key, value, kinds[key])
        else:
            raise ConfigError(f"unknown option {key!r}; see --help for the list")
    if not script.get("out"):
        raise ConfigError("missing out=DIR (the output folder)")
    return script, preset(script["preset"], **overrides)


def render_preview(root: Path, png: Path, shapes=PREVIEW_SHAPES, dpi: int = 100) -> Path:
    """Render a row of generated shapes (headless matplotlib, flat shading) into a PNG.

    When the folder has dense ground truth, vertices are coloured by the position of their template point
    (per class), so the same colour marks the same body point on every shape. Shapes missing from the folder
    are skipped. Returns the PNG path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from shapecorr.data.io import read_mesh

    names = [f"{c}_s{s:02d}_p{p:02d}" for c, s, p in shapes]
    names = [n for n in names if (root / "off" / f"{n}.off").is_file()]
    if not names:
        raise ConfigError("no shape to preview in the folder", root)
    light = np.array([0.35, -0.6, 0.7]) / np.linalg.norm([0.35, -0.6, 0.7])
    fig = plt.figure(figsize=(1.45 * len(names), 2.5))
    for i, name in enumerate(names):
        verts, faces = read_mesh(root / "off" / f"{name}.off")
        colors = _body_point_colors(root, name, len(verts))
        verts = verts @ _PLOT_AXES.T  # files: y up, z forward -> matplotlib: z up, facing -y
        tri = verts[faces]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True) + 1e-12
        shade = 0.35 + 0.65 * np.clip(normal @ light, 0.0, 1.0)
        ax = fig.add_subplot(1, len(names), i + 1, projection="3d")
        ax.add_collection3d(Poly3DCollection(tri, facecolors=np.clip(shade[:, None] * colors[faces].mean(1), 0, 1),
                                             edgecolors="none"))
        centre, radius = (verts.max(0) + verts.min(0)) / 2, (verts.max(0) - verts.min(0)).max() / 2
        for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre):
            setter(c - radius, c + radius)
        ax.view_init(elev=12, azim=PREVIEW_AZIMUTH["quad" if name.startswith("quad") else "human"])
        ax.set_box_aspect((1, 1, 1), zoom=1.35)
        ax.set_axis_off()
        ax.set_title(f"{name}\n{len(verts)} vertices", fontsize=7, y=0.95)
    fig.subplots_adjust(0, 0, 1, 0.92, 0, 0)
    png = Path(png)
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=dpi)
    plt.close(fig)
    return png


def _body_point_colors(root: Path, name: str, n_verts: int):
    """Per-vertex RGB from the dense ground truth (template position -> colour), grey without it."""
    from shapecorr.data.io import read_mesh

    cls = name.split("_")[0]
    dense, template = root / "dense" / f"{name}.npz", root / "templates" / f"{cls}.off"
    if not (dense.is_file() and template.is_file()):
        return np.full((n_verts, 3), 0.7)
    t_verts, t_faces = read_mesh(template)
    lo, hi = t_verts.min(0), t_verts.max(0)
    t_colors = 0.15 + 0.8 * (t_verts - lo) / (hi - lo)
    with np.load(dense, allow_pickle=False) as gt:
        return np.einsum("nj,njk->nk", gt["template_bary"], t_colors[t_faces[gt["template_face"]]])


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if any(a in ("-h", "--help", "help") for a in argv):
        print(_help_text())
        return 0
    parser = argparse.ArgumentParser(add_help=False)
    parser.add_argument("tokens", nargs="*")
    tokens = parser.parse_args(argv).tokens
    try:
        script, cfg = parse_options(tokens)
        start = time.perf_counter()
        root = ensure_synthetic_dataset(Path(script["out"]), cfg, workers=script["workers"],
                                        progress=script["progress"])
        elapsed = time.perf_counter() - start
        n_shapes = len(list((root / "off").glob("*.off")))
        print(f"synthetic dataset: {n_shapes} shapes in {root} ({elapsed:.1f} s, fingerprint {cfg.fingerprint()[:12]})")
        if script["preview"]:
            print(f"preview: {render_preview(root, Path(script['preview']))}")
    except ShapeCorrError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
