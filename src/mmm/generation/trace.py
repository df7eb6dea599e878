"""Plot a decoding trace in the style of the paper's Figures 9 and 10 (supplementary E).

For one sample: a grid of token positions (x) by iterations (y); each cell is coloured by the
confidence of the code drawn there at that iteration, cells re-masked after the iteration are
hatched, positions fixed before (decoded earlier or kept) are left white; beside it, how many
positions stay masked after each iteration.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle


def plot_trace(trace, out_png: str | Path, sample: int = 0, title: str | None = None) -> Path:
    steps = [i for i, active in enumerate(trace.active) if bool(active[sample])]
    if not steps:
        raise ValueError(f"sample {sample} took no decoding iteration (nothing to decode)")
    confidence = np.stack([trace.confidence[i][sample].numpy() for i in steps])  # (iterations, M)
    masked = np.stack([trace.masked[i][sample].numpy() for i in steps])
    length = (
        int(np.isfinite(confidence).any(0).nonzero()[0].max()) + 1
        if np.isfinite(confidence).any()
        else confidence.shape[1]
    )
    confidence, masked = confidence[:, :length], masked[:, :length]
    fig = Figure(figsize=(min(16, 2 + 0.28 * length), 1.2 + 0.45 * len(steps)), dpi=110)
    ax, side = fig.subplots(1, 2, gridspec_kw={"width_ratios": [6, 1]})
    image = ax.imshow(
        np.ma.masked_invalid(confidence), aspect="auto", cmap="viridis", vmin=0.0, vmax=1.0, origin="upper"
    )
    for it, row in enumerate(masked):
        for pos in np.flatnonzero(row):
            ax.add_patch(
                Rectangle(
                    (pos - 0.5, it - 0.5), 1, 1, fill=False, hatch="///", edgecolor="white", linewidth=0
                )
            )
    ax.set_xlabel("token position")
    ax.set_ylabel("iteration")
    ax.set_yticks(range(len(steps)), [str(i + 1) for i in range(len(steps))])
    ax.set_title(title or "confidence of the drawn code (hatched: masked again)", fontsize=9)
    fig.colorbar(image, ax=ax, fraction=0.03, pad=0.01, label="confidence")
    side.barh(range(len(steps)), masked.sum(1), color="#888")
    side.invert_yaxis()
    side.set_yticks([])
    side.set_xlabel("masked after")
    fig.tight_layout()
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png)
    return out_png
