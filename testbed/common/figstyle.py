"""The one style of every figure the testbed draws (matplotlib, Agg backend, imported lazily).

* sizes for IEEE papers: ``column`` = one column (3.5 in wide), ``page`` = both columns
  (7.16 in); the command-line flag ``--figsize column|page`` of every command that plots;
* the format by the file's extension: ``.png`` (300 dpi), ``.pdf`` (fonts embedded as
  TrueType), ``.svg``; anything else is a ``BadInput``;
* mathtext labels ($x_1$, $E_k$, $\\theta_k$, $\\rho_D$), legends below the axes (outside the data);
* the Okabe-Ito palette (safe for the common colour-vision deficiencies); a pair of runs A/B
  (``testbed compare``) is one hue per quantity, A solid and B dashed;
* DoS intervals shaded gray on every time axis (:func:`shade_dos`), named "DoS" in the legend.

Every saved figure carries a digest of the data it drew (:func:`data_digest`: the coordinates of
its lines, images, collections and patches, and its texts, rounded to about 9 significant
digits) in the file's metadata (PNG text chunk ``testbed-data``, PDF ``Subject``, SVG
``Description``). ``docs/make_figures.py --check`` recomputes the figures and compares these
digests, not pixels.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Iterable
from contextlib import AbstractContextManager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import BadInput

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from matplotlib.legend import Legend
    from matplotlib.patches import Patch

#: file formats, by extension
FORMATS = (".png", ".pdf", ".svg")
#: figure widths in inches: one IEEE column, both columns (a page-wide figure*)
WIDTHS = {"column": 3.5, "page": 7.16}
SIZES = tuple(WIDTHS)

# Okabe & Ito (2008), "Color Universal Design": distinguishable with every common colour-vision deficiency
BLUE, VERMILLION, GREEN, ORANGE, PURPLE, SKY, YELLOW, BLACK = (
    "#0072B2", "#D55E00", "#009E73", "#E69F00", "#CC79A7", "#56B4E9", "#F0E442", "#000000")
#: colour cycle: state components, series, attacker kinds, ... in this order
CYCLE = (BLUE, VERMILLION, GREEN, ORANGE, PURPLE, SKY, BLACK)
#: the colour map of fractions and durations (perceptually uniform, colour-vision safe)
CMAP = "cividis"
#: the shade of DoS intervals on time axes
DOS_COLOR = "0.55"
DOS_ALPHA = 0.3
#: line styles of a pair of runs: A, B
AB_STYLES = ("-", "--")

METADATA_KEY = "testbed-data"


def check_path(path: str | Path) -> Path:
    """``path`` if its extension is a known format (``.png``, ``.pdf``, ``.svg``), else ``BadInput``."""
    p = Path(path)
    if p.suffix.lower() not in FORMATS:
        raise BadInput(f"{path}: a figure is written as {', '.join(FORMATS)} (by the extension), "
                       f"not {p.suffix or 'a name without extension'!r}")
    return p


def check_size(size: str) -> str:
    if size not in WIDTHS:
        raise BadInput(f"figure size {size!r}: use one of {', '.join(SIZES)}")
    return size


def rc(size: str = "page") -> dict:
    """matplotlib rcParams of the style (fonts a little larger in a column: it is printed smaller)."""
    check_size(size)
    fs = 8.0 if size == "column" else 9.0
    from cycler import cycler

    return {
        "font.size": fs, "axes.labelsize": fs, "axes.titlesize": fs, "legend.fontsize": fs - 1,
        "xtick.labelsize": fs - 1, "ytick.labelsize": fs - 1, "lines.linewidth": 1.1, "lines.markersize": 3,
        "axes.prop_cycle": cycler(color=list(CYCLE)), "axes.grid": True, "grid.alpha": 0.3, "grid.linewidth": 0.5,
        "legend.frameon": False, "legend.handlelength": 2.2, "image.cmap": CMAP,
        "savefig.dpi": 300, "pdf.fonttype": 42, "ps.fonttype": 42, "svg.hashsalt": "testbed",
        "figure.constrained_layout.use": True, "axes.formatter.use_mathtext": True,
    }


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the Agg backend (no display needed)."""
    os.environ.setdefault("MPLBACKEND", "Agg")
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def subplots(size: str = "page", nrows: int = 1, ncols: int = 1, *, aspect: float = 0.62,
             **kw: Any) -> tuple[Figure, np.ndarray]:
    """``(fig, axes)`` of the style: ``size`` sets the width; the height is ``aspect`` x the width per
    row of a one-column layout (``aspect * width * nrows / ncols``)."""
    plt = pyplot()
    w = WIDTHS[check_size(size)]
    h = aspect * w * nrows / max(ncols, 1)
    fig, axs = plt.subplots(nrows, ncols, figsize=(w, h), squeeze=False, layout="constrained", **kw)
    fig._testbed_size = size
    return fig, axs


def panels(size: str, n: int) -> tuple[int, int]:
    """Rows and columns of ``n`` side-by-side panels: in a row on a page, stacked in a column."""
    return (n, 1) if size == "column" else (1, n)


def style(size: str = "page") -> AbstractContextManager[None]:
    """``with style(size):`` draw a figure in the style (matplotlib reads most settings when an artist is made)."""
    return pyplot().rc_context(rc(size))


def shade_dos(ax: Axes, spans: Iterable[tuple[float, float]], *, T: float = 0.0, label: bool = True) -> None:
    """Shade DoS intervals [(start, end), ...] on a time axis; the first span is labelled "DoS"."""
    first = True
    for a, b in spans:
        ax.axvspan(a, b if b > a else a + max(0.02 * T, 1e-9), color=DOS_COLOR, alpha=DOS_ALPHA, lw=0,
                   label="DoS" if (first and label) else None)
        first = False


def dos_handle(label: str = "DoS") -> Patch:
    """The legend entry of the DoS shading (for legends made of explicit handles)."""
    from matplotlib.patches import Patch

    return Patch(color=DOS_COLOR, alpha=DOS_ALPHA, lw=0, label=label)


def legend_below(fig: Figure, handles: list[Any] | None = None, *, ncol: int | None = None,
                 axes: Iterable[Axes] | None = None) -> Legend | None:
    """One legend under the axes, outside the data (constrained layout makes room for it)."""
    if handles is None:
        handles = []
        seen = set()
        for ax in (axes if axes is not None else fig.axes):
            for h, lab in zip(*ax.get_legend_handles_labels()):
                if lab not in seen and not lab.startswith("_"):
                    seen.add(lab)
                    handles.append(h)
        handles.sort(key=lambda h: h.get_label() == "DoS")  # the shading last, after the data
    if not handles:
        return None
    import re

    import matplotlib as mpl

    # as many columns as the longest entry lets fit in the figure's width (an estimate: mathtext
    # markup is shorter on paper than in the string; a character about half the font size wide)
    plain = [re.sub(r"\\[a-zA-Z]+|[${}_^]", "x", h.get_label()) for h in handles]
    char = 0.5 * mpl.rcParams["legend.fontsize"] / 72 if isinstance(mpl.rcParams["legend.fontsize"], float) else 0.05
    entry = max(len(s) for s in plain) * char + 0.55
    fit = max(1, int(fig.get_figwidth() // entry))
    n = min(ncol or len(handles), fit, len(handles))
    return fig.legend(handles=handles, loc="outside lower center", ncol=n, frameon=False)


# ---------------------------------------------------------------------------- the data a figure drew
def _round(a) -> np.ndarray:
    """Floats rounded to 30 mantissa bits (about 9 significant digits): the last bits of a
    computation do not make a figure stale, a changed value does."""
    a = np.ma.filled(np.ma.asarray(a, dtype=float), np.nan).astype(float).ravel()
    m, e = np.frexp(np.nan_to_num(a, nan=0.0, posinf=0.0, neginf=0.0))
    r = np.ldexp(np.round(m * 2.0**30) / 2.0**30, e)
    return np.where(np.isfinite(a), r, a)


def data_digest(fig: Any) -> str:
    """SHA-256 of what the figure shows: the data of every line, image, collection and patch and
    every text (titles, labels, legends), axes by axes, insets and colorbars included."""
    from matplotlib.axes import Axes

    h = hashlib.sha256()

    def num(tag, a):
        r = _round(a)
        h.update(f"{tag}{r.size}:".encode())
        h.update(np.nan_to_num(r, nan=1e308 * 0.5).tobytes())

    def text(tag, s):
        h.update(f"{tag}:{s}\n".encode())

    for t in fig.texts:
        text("figtext", t.get_text())
    for leg in fig.legends:
        for t in leg.get_texts():
            text("legend", t.get_text())
    for ax in fig.findobj(Axes):
        text("axes", f"{ax.get_title()}|{ax.get_xlabel()}|{ax.get_ylabel()}|{ax.get_xscale()}|{ax.get_yscale()}")
        num("lim", [*ax.get_xlim(), *ax.get_ylim()])
        for ln in ax.lines:
            text("line", ln.get_label())
            num("xy", ln.get_xydata())
        for im in ax.images:
            num("image", im.get_array())
            num("extent", im.get_extent())
        for c in ax.collections:
            text("coll", c.get_label())
            num("offsets", c.get_offsets())
            arr = c.get_array()
            if arr is not None:
                num("array", arr)
            for p in c.get_paths():
                num("path", p.vertices)
        for p in ax.patches:
            text("patch", p.get_label())
            num("patch", p.get_patch_transform().transform(p.get_path().vertices))
        for t in ax.texts:
            text("text", t.get_text())
        leg = ax.get_legend()
        if leg is not None:
            for t in leg.get_texts():
                text("legend", t.get_text())
    return h.hexdigest()


def save(fig: Figure, path: str | Path) -> Path:
    """Write ``fig`` in the format of ``path``'s extension, with the digest of its data in the metadata."""
    path = check_path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    digest = data_digest(fig)
    ext = path.suffix.lower()
    meta: dict[str, str | None]
    if ext == ".png":
        meta = {METADATA_KEY: digest, "Software": "testbed (matplotlib)"}
    elif ext == ".pdf":
        meta = {"Subject": f"{METADATA_KEY} {digest}", "Creator": "testbed", "CreationDate": None}
    else:
        meta = {"Description": f"{METADATA_KEY} {digest}", "Date": None}
    plt = pyplot()
    with plt.rc_context(rc(getattr(fig, "_testbed_size", "page"))):
        fig.savefig(path, metadata=meta)
    plt.close(fig)
    return path


def read_digest(path: str | Path) -> str | None:
    """The data digest stored in a figure file by :func:`save` (None if it has none)."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext == ".png":
        from PIL import Image

        with Image.open(path) as im:
            return getattr(im, "text", {}).get(METADATA_KEY)  # a PNG's text chunks
    data = path.read_bytes()
    key = METADATA_KEY.encode() + b" "
    i = data.find(key)
    if i < 0:
        return None
    return data[i + len(key):i + len(key) + 64].decode()


__all__ = ["FORMATS", "SIZES", "WIDTHS", "CYCLE", "CMAP", "AB_STYLES", "check_path", "check_size", "subplots",
           "panels", "shade_dos", "dos_handle", "legend_below", "data_digest", "save", "read_digest",
           "pyplot", "rc", "style"]
