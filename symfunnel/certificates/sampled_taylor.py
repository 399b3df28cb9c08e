"""`certify.sampled`'s a-priori enclosure of one period in Taylor (mean-value) form (`OnePeriod._taylor`): the
displacement over the period from the rates at the sample and the rates' Jacobian along it, with Coulomb friction's
sign as an input in its hull over the box where the original rates jump (docs/certify.md)."""

from __future__ import annotations

import numpy as np

from .sampled_graph import _dn, _imul, _sum_dn, _sum_up, _up

#: Picard iterations before a box's a-priori enclosure counts as not found
PICARD_ITERATIONS = 8


def taylor(op, FL, FH, kl, kh, tl, th, UL, UH, h, lim):
    """The a-priori enclosure in Taylor (mean-value) form, per box K of sample states: the displacement
    Delta = sigma(t) - sigma_k over the period satisfies Delta in [0, h] D with

        D = R_k + J_t [0, h] + J_sigma Delta  (intersected with the rates over Sigma = K + Delta),

    R_k the rates at the sample under the step's own torque (one function of the sample state: the torque's
    cancellation against alpha2_dot is kept, where the first-order form holds the torque as an independent box)
    and J the rates' Jacobian in (t, sigma) over [t_k, t_k + h] x Sigma with the torque held (interval AD:
    Clarke's Jacobian where sigma' is Lipschitz along the period, which is required: `continuous`, or no
    discontinuity switches on the box). If [0, h] D lies in Delta, the Picard operator maps the continuous
    functions with sigma - sigma_k in Delta into themselves (Schauder; unique by Lipschitz), so the solution
    stays in K + Delta and its rate in D. Where Coulomb friction's sign(dq) is what makes the rates jump
    (`op.n_sw`), the rates take it as inputs sw and D gains J_sw (S - S_k), S and S_k the hulls of sign over the
    period's box and over the sample box: the mean-value theorem in (t, sigma, sw) jointly (a Filippov solution's
    sign in [-1, 1] where dq = 0 included); friction opposing motion keeps forward solutions unique. Returns
    (valid, DL, DH, SL, SH, switched) per box."""
    n2 = 2 * op.n
    K = FL.shape[0]
    ns = op.n_sw
    if ns:
        # the switched signs at the sample (their hull over K) and the rates there with them as inputs
        u0 = np.zeros((K, op.n))
        i = op.i_st
        SKL, SKH = op._signs(np.concatenate([FL[:, :i], u0, FL[:, i:]], 1),
                               np.concatenate([FH[:, :i], u0, FH[:, i:]], 1))
        XL, XH = np.concatenate([FL, SKL], 1), np.concatenate([FH, SKH], 1)
        RL, RH, _ = op.ratek_s_ball.eval_batch(XL, XH, op.ball) if op.ball is not None else \
            op.ratek_s.eval_batch(XL, XH)
    else:
        RL, RH, _ = op.ratek_ball.eval_batch(FL, FH, op.ball) if op.ball is not None else \
            op.ratek.eval_batch(FL, FH)
    fin = np.all(np.isfinite(RL) & np.isfinite(RH), axis=1)
    gl = _dn(h * np.minimum(RL, 0.0))
    gh = _up(h * np.maximum(RH, 0.0))
    w = gh - gl
    valid = np.zeros(K, dtype=bool)
    DL, DH = np.full((K, n2), -np.inf), np.full((K, n2), np.inf)
    SL, SH = kl.copy(), kh.copy()
    sw = np.ones(K, dtype=bool)
    nw = (op.rate_s if ns else op.rate).w_flat.size

    def iterate(al, ah, live):
        # the Picard iteration of Delta from the first guess (al, ah) on the boxes `live`
        for _ in range(PICARD_ITERATIONS):
            idx = np.flatnonzero(live & ~valid)
            if not idx.size:
                break
            sl, sh = _dn(kl[idx] + al[idx]), _up(kh[idx] + ah[idx])
            inside = np.all((sl > -lim) & (sh < lim), axis=1) if lim >= 1.0 else \
                np.all((sl >= -lim) & (sh <= lim), axis=1)
            live[idx[~inside]] = False
            idx, sl, sh = idx[inside], sl[inside], sh[inside]
            if not idx.size:
                break
            n_ = op.n
            RLo = np.concatenate([tl[idx, None], sl, FL[idx, 2 * n_ + 1:op.i_st], UL[idx], FL[idx, op.i_st:]], 1)
            RHi = np.concatenate([th[idx, None], sh, FH[idx, 2 * n_ + 1:op.i_st], UH[idx], FH[idx, op.i_st:]], 1)
            m = idx.size
            if ns:
                # each switched sign in its hull over the period's box: J_s (S - S_k) joins the mean-value form
                SBL, SBH = op._signs(RLo, RHi)
                RLo, RHi = np.concatenate([RLo, SBL], 1), np.concatenate([RHi, SBH], 1)
                NL, NH, nsw = op.rate_s.eval_batch(RLo, RHi)
                JL, JH, _ = op.rate_s.jac.eval_batch(RLo, RHi)
                JL = JL.reshape(m, nw, n2).transpose(0, 2, 1)
                JH = JH.reshape(m, nw, n2).transpose(0, 2, 1)
                ql, qh = _imul(JL[:, :, nw - ns:], JH[:, :, nw - ns:], (SBL - SKH[idx])[:, None, :],
                               (SBH - SKL[idx])[:, None, :])
                jsl, jsh = _sum_dn(ql, 2), _sum_up(qh, 2)
                nsw = np.asarray(nsw, bool)
                moved = nsw | np.any(SBL != SBH, axis=1)
            else:
                NL, NH, nsw = op.rate.eval_batch(RLo, RHi)
                JL, JH, _ = op.rate.jac.eval_batch(RLo, RHi)
                JL = JL.reshape(m, nw, n2).transpose(0, 2, 1)
                JH = JH.reshape(m, nw, n2).transpose(0, 2, 1)
                jsl = jsh = np.zeros((m, n2))
                nsw = moved = np.asarray(nsw, bool)
            # J_t [0, h]
            tL = _dn(h * np.minimum(JL[:, :, 0], 0.0))
            tH = _up(h * np.maximum(JH[:, :, 0], 0.0))
            # J_sigma Delta, interval matrix times interval vector, outward
            pl, ph = _imul(JL[:, :, 1:n2 + 1], JH[:, :, 1:n2 + 1], al[idx][:, None, :], ah[idx][:, None, :])
            cl, ch = _sum_dn(pl, 2), _sum_up(ph, 2)
            dl = _dn(_dn(_dn(RL[idx] + tL) + cl) + jsl)
            dh = _up(_up(_up(RH[idx] + tH) + ch) + jsh)
            ok_ = np.isfinite(dl) & np.isfinite(dh)
            dl = np.where(ok_, np.maximum(dl, NL), NL)
            dh = np.where(ok_, np.minimum(dh, NH), NH)
            smooth = op.continuous | ~nsw
            fin2 = np.all(np.isfinite(dl) & np.isfinite(dh), axis=1) & smooth
            live[idx[~fin2]] = False
            nl, nh = _dn(h * np.minimum(dl, 0.0)), _up(h * np.maximum(dh, 0.0))
            cont = fin2 & np.all((nl >= al[idx]) & (nh <= ah[idx]), axis=1)
            g = idx[cont]
            valid[g] = True
            DL[g], DH[g], SL[g], SH[g] = dl[cont], dh[cont], sl[cont], sh[cont]
            sw[g] = moved[cont]
            grow = fin2 & ~cont
            gi = idx[grow]
            ww = nh[grow] - nl[grow]
            al[gi] = np.where(nl[grow] < al[gi], _dn(nl[grow] - 0.1 * ww - 1e-12), al[gi])
            ah[gi] = np.where(nh[grow] > ah[gi], _up(nh[grow] + 0.1 * ww + 1e-12), ah[gi])

    # Delta: first the first-order step widened by a tenth both ways; where that finds no enclosure, widened on
    # the sides it moves to only (a side where the rate at the sample is <= 0, say at a face of S where the flow
    # points inward, stays at the sample's value: widened both ways it crosses the funnel in a stiff layer where
    # h |sigma'| is near the gap; the symmetric guess, with its slack, needs fewer iterations elsewhere)
    iterate(_dn(gl - 0.1 * w - 1e-12), _up(gh + 0.1 * w + 1e-12), fin.copy())
    again = fin & ~valid
    if again.any():
        iterate(np.where(RL < 0, _dn(gl - 0.1 * w - 1e-12), -1e-12),
                np.where(RH > 0, _up(gh + 0.1 * w + 1e-12), 1e-12), again)
    return valid, DL, DH, SL, SH, sw
