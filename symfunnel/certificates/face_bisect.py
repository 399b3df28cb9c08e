"""certify.containment's bisection of the faces' open boxes, a batch at a time: per box the split coordinate of
largest sensitivity |dn/dx| * width (else of largest width relative to the face), halved at its midpoint.

One numpy pass per face over the batch's open boxes, in place of a Python loop of a dozen small numpy calls per box
(about 10 % of containment's branch and bound on derivations/paper_small_dead_zone_projection.toml): every entry is
the same product, comparison and midpoint as box by box, and the children come out in the same order."""

from __future__ import annotations

import numpy as np


def bisect_open(batch: list[tuple], open_rows: np.ndarray, J: np.ndarray, pos: np.ndarray, split_of: list,
                faces: list[dict], w_flat) -> tuple[list[tuple], int | None]:
    """The children of the batch's open boxes `open_rows` (box i: batch[i] = (lo, hi, face, volume) in its face's
    split coordinates split_of[face]; J (K, n_out, n_w) the form's |Jacobian| bound, pos[i] the face's output),
    in the order box by box, each box's lower half then its upper half; and the first open row too thin to halve
    (its midpoint not strictly inside), else None (the children are then all of them)."""
    wpos = {int(j): i for i, j in enumerate(w_flat)}
    rows = np.asarray(open_rows, dtype=int)
    fk = np.array([batch[k][2] for k in rows], dtype=int)
    s_all = np.zeros(rows.size, dtype=int)
    m_all = np.zeros(rows.size)
    for f in np.unique(fk):
        g = np.flatnonzero(fk == f)
        ks = rows[g]
        split = split_of[f]
        lo = np.array([batch[k][0] for k in ks]).reshape(len(ks), len(split))
        hi = np.array([batch[k][1] for k in ks]).reshape(len(ks), len(split))
        width = hi - lo
        wi = np.array([wpos.get(int(j), -1) for j in split], dtype=int)
        Jw = J[ks, pos[ks]][:, np.maximum(wi, 0)] if J.shape[-1] else np.zeros_like(width)   # no w: all nan
        with np.errstate(invalid="ignore"):                  # inf * 0 of a masked or nan entry: scored 0 below
            sens = np.where(wi >= 0, Jw * width, np.nan)
        flo, fhi = faces[f]["lo"][split], faces[f]["hi"][split]
        rel = width / np.where(fhi > flo, fhi - flo, 1.0)
        score = np.where(np.isfinite(sens) & (sens > 0), sens, 0.0)
        s = np.where(np.any(score > 0, axis=1), np.argmax(score, axis=1), np.argmax(rel, axis=1))
        r = np.arange(len(ks))
        s_all[g] = s
        m_all[g] = 0.5 * lo[r, s] + 0.5 * hi[r, s]
    children = []
    for i, k in enumerate(rows):
        lo, hi, f, vol = batch[k]
        s, m = int(s_all[i]), m_all[i]
        if not (lo[s] < m < hi[s]):
            return children, int(k)
        h1, l2 = hi.copy(), lo.copy()
        h1[s] = m
        l2[s] = m
        children.append((lo, h1, f, vol / 2))
        children.append((l2, hi, f, vol / 2))
    return children, None
