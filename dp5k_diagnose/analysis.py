"""Show what a model gets wrong: masked residuals against the variables that explain DP errors, measured
versus predicted DP disparity, the L/R brightness ratio across the field, and PSFs estimated from data.

Everything is computed from images (dataset format v1) and a model's predictions; nothing reads planted
metadata. All functions are vectorised over pixels and tiles.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .data import Sample

Predict = Callable[[Sample], tuple[Tensor, Tensor]]
VARIABLES = ("x", "y", "radius", "coc_px", "abs_coc_px", "depth_mm", "intensity", "local_contrast")


def _local_std(img: Tensor, k: int = 5) -> Tensor:
    g = img.mean(1, keepdim=True)
    pad = (k // 2,) * 4
    m = F.avg_pool2d(F.pad(g, pad, mode="replicate"), k, stride=1)
    m2 = F.avg_pool2d(F.pad(g * g, pad, mode="replicate"), k, stride=1)
    return (m2 - m * m).clamp(min=0).sqrt()


def _binned(v: np.ndarray, cols: dict[str, np.ndarray], n_bins: int = 8) -> dict[str, list[float]]:
    """Quantile bins of ``v``: centres and the mean of each column per bin."""
    if v.size == 0:
        return {"bin_center": []}
    edges = np.unique(np.quantile(v, np.linspace(0, 1, n_bins + 1)))
    if edges.size < 2:
        edges = np.array([v.min(), v.max() + 1e-6])
    idx = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, edges.size - 2)
    cnt = np.bincount(idx, minlength=edges.size - 1).astype(np.float64)
    out: dict[str, list[float]] = {"bin_center": (np.bincount(idx, v, edges.size - 1) / np.maximum(cnt, 1)).tolist(), "count": cnt.tolist()}
    for name, c in cols.items():
        out[name] = (np.bincount(idx, c, edges.size - 1) / np.maximum(cnt, 1)).tolist()
    return out


def residual_tables(predict: Predict, samples: list[Sample], max_px: int = 400_000, seed: int = 0) -> dict[str, Any]:
    """Mean |residual| of L, R, L+R and L-R (and mean signed L-R) per bin of each explanatory variable,
    plus per colour channel. Residual = prediction - measurement, over valid pixels."""
    rng = np.random.default_rng(seed)
    rows: dict[str, list[np.ndarray]] = {k: [] for k in VARIABLES + ("eL", "eR", "eS", "eD", "eD_signed")}
    per_ch = np.zeros((3, 4))
    n_ch = 0.0
    with torch.no_grad():
        for s in samples:
            b = s.batch
            pl, pr = predict(s)
            eL, eR = pl - b.left, pr - b.right
            eS, eD = eL + eR, eL - eR
            m = b.valid.expand_as(eL)
            for c in range(3):
                mc = m[:, c]
                per_ch[c] += [float(t[:, c][mc].abs().sum()) for t in (eL, eR, eS, eD)]
            n_ch += float(m[:, 0].sum())
            vars_ = {
                "x": s.field[:, :1], "y": s.field[:, 1:2],
                "radius": ((s.field[:, :1] ** 2 + s.field[:, 1:2] ** 2) / 2).sqrt(),
                "coc_px": b.coc_px, "abs_coc_px": b.coc_px.abs(), "depth_mm": b.depth_mm,
                "intensity": (b.left + b.right).mean(1, keepdim=True), "local_contrast": _local_std(b.sharp),
            }
            mv = b.valid[:, 0]
            for k, v in vars_.items():
                rows[k].append(v[:, 0][mv].numpy())
            rows["eL"].append(eL.abs().mean(1)[mv].numpy())
            rows["eR"].append(eR.abs().mean(1)[mv].numpy())
            rows["eS"].append(eS.abs().mean(1)[mv].numpy())
            rows["eD"].append(eD.abs().mean(1)[mv].numpy())
            rows["eD_signed"].append(eD.mean(1)[mv].numpy())
    flat = {k: np.concatenate(v) if v else np.zeros(0) for k, v in rows.items()}
    n = flat["x"].size
    sel = rng.choice(n, max_px, replace=False) if n > max_px else np.arange(n)
    cols = {"L": flat["eL"][sel], "R": flat["eR"][sel], "L+R": flat["eS"][sel], "L-R": flat["eD"][sel], "L-R signed": flat["eD_signed"][sel]}
    tables = {k: _binned(flat[k][sel], cols) for k in VARIABLES}
    tables["channel"] = {"bin_center": ["R", "G", "B"], **{name: (per_ch[:, i] / max(n_ch, 1)).tolist() for i, name in enumerate(("L", "R", "L+R", "L-R"))}}
    return tables


def tile_disparity(left: Tensor, right: Tensor, mask: Tensor, tile: int = 16, iters: int = 3) -> tuple[Tensor, Tensor]:
    r"""Local horizontal DP disparity per tile by iterated Lucas-Kanade (R relative to L, + = right).

    Per tile, :math:`d = \sum g_x (L - R_w) / \sum g_x^2` with :math:`R_w` the right view warped back by the
    current estimate and :math:`g_x` the mean horizontal gradient of both views.

    Returns:
        disparity (B, nty, ntx) px and texture weight (B, nty, ntx) (sum of g_x^2; low = unreliable).
    """
    L = left.mean(1, keepdim=True)
    R = right.mean(1, keepdim=True)
    B, _, H, W = L.shape
    nty, ntx = H // tile, W // tile
    d = torch.zeros(B, 1, nty, ntx)
    w = torch.zeros_like(d)
    for _ in range(iters):
        dmap = F.interpolate(d, size=(nty * tile, ntx * tile), mode="nearest")
        dmap = F.pad(dmap, (0, W - ntx * tile, 0, H - nty * tile), mode="replicate")
        xs = torch.arange(W, dtype=L.dtype).view(1, 1, W).expand(B, H, W) + dmap[:, 0]
        ys = torch.arange(H, dtype=L.dtype).view(1, H, 1).expand(B, H, W)
        grid = torch.stack([xs / (W - 1) * 2 - 1, ys / (H - 1) * 2 - 1], -1)
        Rw = F.grid_sample(R, grid, mode="bilinear", padding_mode="border", align_corners=True)
        g = 0.5 * ((L[..., 2:] - L[..., :-2]) + (Rw[..., 2:] - Rw[..., :-2])) / 2
        g = F.pad(g, (1, 1))
        m = mask.float()
        num = F.avg_pool2d((g * (L - Rw) * m)[..., : nty * tile, : ntx * tile], tile)
        den = F.avg_pool2d((g * g * m)[..., : nty * tile, : ntx * tile], tile)
        # R(x) = L(x - d): R_w(x) = R(x + d_est) ~ L(x) + (d_est - d) g, so d = d_est + sum g (L - R_w) / sum g^2
        d = d + num / den.clamp(min=1e-12)
        d = d.clamp(-20, 20)
        w = den
    return d[:, 0], w[:, 0]


def disparity_table(predict: Predict, samples: list[Sample], tile: int = 16) -> dict[str, Any]:
    """Measured vs predicted tile disparity against the tile's median CoC (textured, constant-CoC tiles)."""
    coc_l, meas_l, pred_l = [], [], []
    with torch.no_grad():
        for s in samples:
            b = s.batch
            pl, pr = predict(s)
            dm, wm = tile_disparity(b.left, b.right, b.valid, tile)
            dp, _ = tile_disparity(pl, pr, b.valid, tile)
            B, _, H, W = b.coc_px.shape
            nty, ntx = H // tile, W // tile
            c = b.coc_px[..., : nty * tile, : ntx * tile].reshape(B, nty, tile, ntx, tile).permute(0, 1, 3, 2, 4).reshape(B, nty, ntx, -1)
            v = b.valid[..., : nty * tile, : ntx * tile].reshape(B, nty, tile, ntx, tile).permute(0, 1, 3, 2, 4).reshape(B, nty, ntx, -1)
            cmed = c.median(-1).values
            crange = c.amax(-1) - c.amin(-1)
            ok = v.all(-1) & (crange < 1.0) & (wm > wm.flatten().quantile(0.25))
            coc_l.append(cmed[ok].numpy())
            meas_l.append(dm[ok].numpy())
            pred_l.append(dp[ok].numpy())
    coc = np.concatenate(coc_l) if coc_l else np.zeros(0)
    meas = np.concatenate(meas_l) if meas_l else np.zeros(0)
    pred = np.concatenate(pred_l) if pred_l else np.zeros(0)
    out: dict[str, Any] = {"tile_px": tile, "n_tiles": int(coc.size), "coc_px": coc.tolist(), "measured_px": meas.tolist(), "predicted_px": pred.tolist()}
    if coc.size >= 3 and np.ptp(coc) > 0:
        out["measured_slope_px_per_coc"] = float(np.polyfit(coc, meas, 1)[0])
        out["predicted_slope_px_per_coc"] = float(np.polyfit(coc, pred, 1)[0])
    return out


def lr_ratio_table(predict: Predict, samples: list[Sample], n_bins: int = 8) -> dict[str, Any]:
    """Mean L / mean R per band of field x (and y), measured and predicted."""
    xs, ys, ml, mr, pl_, pr_ = [], [], [], [], [], []
    with torch.no_grad():
        for s in samples:
            b = s.batch
            pl, pr = predict(s)
            m = b.valid[:, 0]
            xs.append(s.field[:, 0][m].numpy()); ys.append(s.field[:, 1][m].numpy())
            ml.append(b.left.mean(1)[m].numpy()); mr.append(b.right.mean(1)[m].numpy())
            pl_.append(pl.mean(1)[m].numpy()); pr_.append(pr.mean(1)[m].numpy())
    cat = lambda a: np.concatenate(a) if a else np.zeros(0)  # noqa: E731
    x, y, ml_, mr_, pl2, pr2 = map(cat, (xs, ys, ml, mr, pl_, pr_))
    out: dict[str, Any] = {}
    for name, v in (("x", x), ("y", y)):
        edges = np.linspace(-1, 1, n_bins + 1)
        idx = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, n_bins - 1)
        cnt = np.bincount(idx, minlength=n_bins)

        def ratio(a: np.ndarray, c: np.ndarray) -> list[float | None]:
            r = np.bincount(idx, a, n_bins) / np.maximum(np.bincount(idx, c, n_bins), 1e-12)
            return [float(x) if n > 0 else None for x, n in zip(r, cnt)]
        out[name] = {"bin_center": ((edges[:-1] + edges[1:]) / 2).tolist(), "measured": ratio(ml_, mr_), "predicted": ratio(pl2, pr2)}
    return out


def estimate_psfs(predict: Predict, samples: list[Sample], coc_bins: int = 4, tile: int = 32, ksize: int = 15, lam: float = 1e-3) -> list[dict[str, Any]]:
    r"""L/R PSFs estimated from data per CoC bin and field zone (centre / edge), measured vs model.

    Wiener estimate pooled over constant-CoC tiles: :math:`\hat K = \sum \bar S V / (\sum |S|^2 + \lambda \sum |S|^2/n)`
    with S, V the windowed tile spectra of the sharp image and a view; the same estimator on the model's
    views gives the model's PSF, so both carry the same estimation bias.
    """
    win = torch.hann_window(tile, periodic=False)
    win2 = (win[:, None] * win[None, :])
    acc: dict[tuple[int, int], dict[str, Tensor]] = {}
    cocs: list[np.ndarray] = []
    tiles_all = []
    with torch.no_grad():
        for s in samples:
            b = s.batch
            pl, pr = predict(s)
            B, _, H, W = b.sharp.shape
            nty, ntx = H // tile, W // tile
            if nty == 0 or ntx == 0:
                continue

            def tiles(img: Tensor) -> Tensor:
                C = img.shape[1]
                t = img[..., : nty * tile, : ntx * tile].reshape(B, C, nty, tile, ntx, tile).permute(0, 2, 4, 1, 3, 5)
                return t.reshape(B * nty * ntx, C, tile, tile)

            c = tiles(b.coc_px)
            v = tiles(b.valid.float())
            r = tiles(((s.field[:, :1] ** 2 + s.field[:, 1:2] ** 2) / 2).sqrt())
            ok = (v.amin((1, 2, 3)) > 0) & ((c.amax((1, 2, 3)) - c.amin((1, 2, 3))) < 1.0)
            if not ok.any():
                continue
            tiles_all.append((c[ok].mean((1, 2, 3)), r[ok].mean((1, 2, 3)), tiles(b.sharp)[ok], tiles(b.left)[ok], tiles(b.right)[ok], tiles(pl)[ok], tiles(pr)[ok]))
            cocs.append(c[ok].mean((1, 2, 3)).numpy())
    if not tiles_all:
        return []
    call = np.concatenate(cocs)
    edges = np.unique(np.quantile(call, np.linspace(0, 1, coc_bins + 1)))
    for cm, rm, S, L, R, PL, PR in tiles_all:
        bidx = np.clip(np.searchsorted(edges, cm.numpy(), side="right") - 1, 0, max(edges.size - 2, 0))
        zone = (rm.numpy() > 0.5).astype(int)
        fs = torch.fft.rfft2((S - S.mean((2, 3), keepdim=True)) * win2)
        for name, V in (("L", L), ("R", R), ("PL", PL), ("PR", PR)):
            fv = torch.fft.rfft2((V - V.mean((2, 3), keepdim=True)) * win2)
            num = (fs.conj() * fv).sum(1)
            den = (fs.abs() ** 2).sum(1)
            for i in range(num.shape[0]):
                key = (int(bidx[i]), int(zone[i]))
                d = acc.setdefault(key, {})
                d[name] = d.get(name, 0) + num[i]
                d[name + "_den"] = d.get(name + "_den", 0) + den[i]
                if name == "L":
                    d["coc_sum"] = d.get("coc_sum", 0) + float(cm[i])
                    d["n"] = d.get("n", 0) + 1
    out = []
    h = ksize // 2
    for (bi, zone), d in sorted(acc.items()):
        entry: dict[str, Any] = {"coc_px": float(d["coc_sum"] / d["n"]), "zone": "edge" if zone else "centre", "n_tiles": int(d["n"])}
        for name in ("L", "R", "PL", "PR"):
            den = d[name + "_den"]
            k = torch.fft.irfft2(d[name] / (den + lam * den.mean()), s=(tile, tile))
            k = torch.roll(k, (h, h), (0, 1))[:ksize, :ksize]
            k = k / k.sum().clamp(min=1e-8)
            xs = torch.arange(ksize, dtype=k.dtype) - h
            entry[name] = k.numpy().round(5).tolist()
            entry[name + "_centroid_x_px"] = float((k.sum(0) * xs).sum())
        entry["measured_separation_px"] = entry["R_centroid_x_px"] - entry["L_centroid_x_px"]
        entry["model_separation_px"] = entry["PR_centroid_x_px"] - entry["PL_centroid_x_px"]
        out.append(entry)
    return out
