"""The relocalisation bench's pictures (``bench/accuracy_reloc.py``): a t-SNE of the two
traversals (thesis fig. 5.4) and a retrieval panel."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["plot_tsne", "plot_panel"]


def plot_tsne(path: Path, raw: tuple, learned: tuple, conditions: list[str], seed: int) -> None:
    """Two t-SNE panels (layer-21 features | learned embeddings), coloured by traversal."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from sklearn.decomposition import PCA
    from sklearn.manifold import TSNE

    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    for ax, (title, (a, b)) in zip(
        axes, (("ENet layer-21 features", raw), ("learned embedding (eq. 5.1)", learned))
    ):
        x = np.concatenate([a, b]).astype(np.float64)
        n = x.shape[0]
        dims = min(50, n - 1, x.shape[1])
        if x.shape[1] > dims:
            x = PCA(n_components=dims, random_state=seed).fit_transform(x)
        perplexity = float(min(30.0, max(2.0, (n - 1) / 3.0)))
        y = TSNE(
            n_components=2, perplexity=perplexity, init="pca", random_state=seed
        ).fit_transform(x)
        ax.scatter(y[: len(a), 0], y[: len(a), 1], s=6, label=f"database ({conditions[0]})")
        ax.scatter(y[len(a) :, 0], y[len(a) :, 1], s=6, label=f"queries ({conditions[1]})")
        ax.set_title(title)
        ax.set_xticks([])
        ax.set_yticks([])
        ax.legend(loc="best", fontsize=8)
    fig.suptitle("t-SNE of the two traversals (thesis fig. 5.4)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_panel(path: Path, db, qr, retrieval: dict, rows: int = 4) -> None:
    """Query | top-3 database images (learned embedding, whole base); green = correct."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keep = np.flatnonzero(retrieval["keep"])
    picks = keep[np.linspace(0, len(keep) - 1, min(rows, len(keep))).round().astype(int)]
    ranked, _ = retrieval["index"]["learned"].query(retrieval["q_learned"][picks], k=3)
    fig, axes = plt.subplots(len(picks), 4, figsize=(12, 2.4 * len(picks)), squeeze=False)
    for r, (q, row) in enumerate(zip(picks, ranked)):
        truth = set(retrieval["truth"][q].tolist())
        axes[r, 0].imshow(qr.images[q])
        axes[r, 0].set_title(f"query {q} ({qr.condition})", fontsize=8)
        for c, m in enumerate(row, start=1):
            ax = axes[r, c]
            if m < 0:
                ax.axis("off")
                continue
            ax.imshow(db.images[m])
            ok = int(m) in truth
            for spine in ax.spines.values():
                spine.set_edgecolor("green" if ok else "red")
                spine.set_linewidth(3)
            ax.set_title(f"#{c}: base {m} ({'ok' if ok else 'wrong'})", fontsize=8)
        for ax in axes[r]:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
