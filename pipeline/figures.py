"""Figures shared by the reports: the crop grid that compares images side by side.

``crop_grid`` draws one row per frame and one column per image (e.g. GT1 / GT_clean / GT2 for
the cleaner, noisy / OIDN / Isik / ours / GT_clean for the evaluator). Each row shows the same
``size``² window of every image, picked where the row's reference image has the most gradient
energy (where blur and residual noise show), gamma-tonemapped for display (paper eq. 4,
``pipeline.metrics.gamma_compress``). ``plot_curves``: a training run's curves (named (x, y) series, log y
when every value is positive). ``contact_sheet``: whole images in a labelled grid (every validation
scene; random scenes, each exposed by itself: ``exposed``).
``animated_strip``: a sequence as an animated GIF, one column per method.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .exr import atomic_write_bytes
from .metrics import LUMINANCE, gamma_compress, linear_to_srgb, reinhard


def detail_crop(img: np.ndarray, size: int) -> tuple[int, int]:
    """Top-left corner of the ``size``² window with the most gradient energy (where blur shows)."""
    lum = img.mean(axis=2)
    g = np.abs(np.diff(lum, axis=0))[:, :-1] + np.abs(np.diff(lum, axis=1))[:-1, :]
    h, w = g.shape
    size = min(size, h, w)
    best, corner = -1.0, (0, 0)
    step = max(1, size // 4)
    for y in range(0, h - size + 1, step):
        for x in range(0, w - size + 1, step):
            e = float(g[y:y + size, x:x + size].sum())
            if e > best:
                best, corner = e, (y, x)
    return corner


def crop_grid(rows: list[tuple[str, list[np.ndarray | None]]], titles: list[str], path: Path, size: int = 64,
              reference: int = -1) -> None:
    """Save a grid of crops: ``rows`` = [(row label, [HDR image (H, W, 3) or None per column])].

    The crop window of a row is chosen on its image number ``reference`` (default: the last
    column, the ground truth). A ``None`` cell is left blank with "n/a" (a method that did not run).
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not rows:
        return
    cols = len(titles)
    fig, axes = plt.subplots(len(rows), cols, figsize=(2.5 * cols, 2.6 * len(rows)), squeeze=False)
    for r, (label, imgs) in enumerate(rows):
        ref = imgs[reference]
        y, x = detail_crop(ref, size) if ref is not None else (0, 0)
        for c, (name, img) in enumerate(zip(titles, imgs)):
            ax = axes[r][c]
            if img is None:
                ax.text(0.5, 0.5, "n/a", ha="center", va="center", transform=ax.transAxes)
            else:
                crop = np.clip(gamma_compress(img[y:y + size, x:x + size]), 0, 1)
                ax.imshow(crop, interpolation="nearest")
            ax.set_xticks([]), ax.set_yticks([])
            if r == 0:
                ax.set_title(name, fontsize=9)
            if c == 0:
                ax.set_ylabel(label, fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)


# Mid-grey: where ``exposed`` puts an image's log-average luminance (Reinhard's key value).
MID_GREY = 0.18


def exposed(rgb: np.ndarray) -> np.ndarray:
    """Display values in [0, 1] of an HDR image (H, W, 3) exposed by itself: scaled so that its log-average
    luminance is ``MID_GREY``, Reinhard-tonemapped (paper eq. 7) and sRGB-encoded. Images of very
    different brightness all read; their brightness is then not comparable."""
    rgb = np.asarray(rgb, dtype=np.float64)
    lum = np.clip(rgb @ LUMINANCE, 0.0, None)
    key = max(float(np.exp(np.mean(np.log(lum + 1e-4)))), 1e-4)
    return linear_to_srgb(reinhard(rgb * (MID_GREY / key)))


def contact_sheet(cells: list[tuple[str, np.ndarray]], path: Path, cols: int = 6, title: str | None = None,
                  exposure: bool = False, cell: float = 2.1) -> None:
    """Save whole HDR images (H, W, 3) in a grid of ``cols`` columns of ``cell`` inches, each under its label and
    shown pixel for pixel (no interpolation); written via a temporary name. Tonemap: the gamma curve of
    ``crop_grid`` (paper eq. 4), one exposure for all; with ``exposure`` each image by its own (``exposed``).
    ValueError when there is no image."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not cells:
        raise ValueError(f"{path}: a contact sheet needs at least one image")
    rows = -(-len(cells) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(cell * cols, (cell + 0.2) * rows), squeeze=False)
    for k, ax in enumerate(axes.ravel()):
        ax.set_xticks([]), ax.set_yticks([])
        if k >= len(cells):
            ax.axis("off")
            continue
        label, img = cells[k]
        shown = exposed(img) if exposure else np.clip(gamma_compress(img), 0, 1)
        ax.imshow(shown, interpolation="nearest")
        ax.set_title(label, fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=90)


def save_figure(fig, path: str | Path, **kwargs) -> None:
    """``fig.savefig`` to a temporary name, then renamed onto ``path`` (a killed or failed write leaves no
    half of a figure; a full disk is a one-line ``StoreWriteError``); closes ``fig``."""
    import matplotlib.pyplot as plt

    path = Path(path)
    try:
        atomic_write_bytes(path, lambda tmp: fig.savefig(tmp, format=path.suffix.lstrip(".") or "png", **kwargs))
    finally:
        plt.close(fig)


def plot_curves(path: Path, curves: dict[str, list[tuple[float, float]]], title: str, xlabel: str = "epoch",
                ylabel: str = "loss", right: dict[str, list[tuple[float, float]]] | None = None,
                right_label: str = "", log: bool | None = None) -> None:
    """Named (x, y) series as a PNG, written atomically; ``right`` series get their own y axis; ``log``: a log
    y axis (None: when every value is positive)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 4), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    values = []
    for name, pts in curves.items():
        if pts:
            ax.plot(*zip(*pts), "o-" if len(pts) < 60 else "-", label=name, markersize=3)
            values += [y for _, y in pts]
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if log or (log is None and values and all(v > 0 for v in values)):
        ax.set_yscale("log")
    ax.grid(True, alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    if right:
        ax2 = ax.twinx()
        for i, (name, pts) in enumerate(right.items()):
            if pts:
                ax2.plot(*zip(*pts), "s--" if i == 0 else ":", color=f"C{3 + i}", label=name, markersize=3)
        ax2.set_ylabel(right_label)
        h2, l2 = ax2.get_legend_handles_labels()
        handles, labels = handles + h2, labels + l2
    ax.set_title(title)
    ax.legend(handles, labels)
    fig.tight_layout()
    atomic_write_bytes(path, lambda tmp: fig.savefig(tmp, format="png"))


# how long the strip shows each frame: slow enough to compare the columns
STRIP_MS_PER_FRAME = 500


def animated_strip(titles: list[str], frames: list[list[np.ndarray | None]], path: Path) -> None:
    """An animated GIF that plays a sequence side by side: ``frames[t]`` holds frame t's HDR image (H, W, 3) per
    column of ``titles`` (None: a grey cell), gamma-tonemapped, each pixel drawn as a square block (cells at least
    160 pixels wide, room for a title), the column's title and the frame number (1-based, as the report's tables)
    above it. Written atomically; loops forever."""
    from PIL import Image, ImageDraw

    if not frames or not titles:
        return
    h, w = next(img.shape[:2] for row in frames for img in row if img is not None)
    scale = max(1, -(-160 // w))
    cell_w, cell_h, band = w * scale, h * scale, 14
    pictures = []
    for t, row in enumerate(frames):
        canvas = Image.new("RGB", (cell_w * len(titles), cell_h + band), (24, 24, 24))
        draw = ImageDraw.Draw(canvas)
        for c, (title, img) in enumerate(zip(titles, row)):
            if img is None:
                canvas.paste((96, 96, 96), (c * cell_w, band, (c + 1) * cell_w, band + cell_h))
            else:
                rgb = (np.clip(gamma_compress(np.asarray(img, np.float32)), 0, 1) * 255 + 0.5).astype(np.uint8)
                cell = Image.fromarray(rgb).resize((cell_w, cell_h), Image.NEAREST)
                canvas.paste(cell, (c * cell_w, band))
            draw.text((c * cell_w + 3, 1), title if c else f"{title}  #{t + 1}", fill=(230, 230, 230))
        pictures.append(canvas)

    def write(tmp: str) -> None:
        pictures[0].save(tmp, format="GIF", save_all=True, append_images=pictures[1:], duration=STRIP_MS_PER_FRAME, loop=0)

    atomic_write_bytes(Path(path), write)
