"""``default``'s step compiled with numba: the same arithmetic as ``DefaultState.step_numpy``,
channel by channel in one call (tests/test_default.py checks them against each other on real
motion).  The regression matrix of the current missing pattern comes from the model's cache;
only the per-frame work is here.  Used where ``lacuna.jit.enabled()``; else the numpy step serves.
"""
from __future__ import annotations

import numpy as np

from lacuna.jit import jit


@jit
def _wrap(x):
    return (x + 180.0) % 360.0 - 180.0


@jit
def _hat(knots, t):
    """(i, f): t's place on the piecewise-linear knots, clamped at both ends (value = v[i] (1 - f) + v[i + 1] f)."""
    K = knots.shape[0]
    if t <= knots[0]:
        p = 0.0
    elif t >= knots[K - 1]:
        p = K - 1.0
    else:
        s = 0
        while knots[s + 1] <= t:
            s += 1
        p = (t - knots[s]) * (1.0 / (knots[s + 1] - knots[s])) + s
    i = min(int(p), K - 2)
    return i, p - i


@jit
def _knot(W, g, t, knots):
    i, f = _hat(knots, t)
    return W[g, i] * (1.0 - f) + W[g, i + 1] * f


@jit
def _rho(ER, EH, NE, g, n0):
    """Group g's shadow ratio for its gates (blend.state.gate): its own, or while it has had fewer than
    ``n0`` checks, mixed with the ratio of all groups' sums (1 before any check)."""
    rho = (ER[g] + 1e-9) / (EH[g] + 1e-9)
    if n0 <= 0.0:
        return rho
    w = min(NE[g] / n0, 1.0)
    if w >= 1.0:
        return rho
    sr = 0.0
    sh = 0.0
    for i in range(ER.shape[0]):
        sr += ER[i]
        sh += EH[i]
    return w * rho + (1.0 - w) * (sr + 1e-9) / (sh + 1e-9)


@jit
def _features_all(x, ri, mean, mu, Ls, hist, pos, zf):
    """Every regression feature of frame x (blend.state.DefaultState._features with back 0)."""
    n = hist.shape[0]
    Rn = ri.shape[0]
    for o in range(zf.shape[0]):
        b = o // Rn
        c = ri[o % Rn]
        if b == 0:
            v = x[c] - mean[c]
        else:
            v = x[c] - hist[(pos - Ls[b - 1] + 1 + n) % n, c]
        zf[o] = _wrap(v) - mu[o]


@jit
def _guard_update(f, obs, last, ang, group, mean, ri, mu, Ls, hist, pos, knots, wv, wl, wr, wg, d, d2, a, fps, vcap, vgain,
                  h, vgap, k, gz, gzf, gpar, gcols, gptr, gsh, gpos, vk, vh, vv, voff, GS, sv, sh_m, sh_nm, sh_O, sh_nO, sh_B,
                  ER, EH, NE, gate_rho, gate_weak, gate_n0, Lm, gbuf, gbin):
    """blend.guard.guard_update, channel by channel (``gbuf``: the state's scratch, 2 C + len(mu))."""
    G = GS.shape[0]
    B = GS.shape[1]
    for g in range(G):
        for b in range(B):
            for q in range(6):
                GS[g, b, q] *= gpar[0]
    cnt = int(sv[5])
    sv[5] += 1
    if cnt <= Lm or sv[2] == 0.0:
        return
    Kmax = gz[B - 1]
    C = f.shape[0]
    x = gbuf[:C]  # scratch of the state: no allocation per step
    zf = gbuf[C:C + mu.shape[0]]
    Qb = gbuf[C + mu.shape[0]:]
    for j in range(C):
        x[j] = f[j] if obs[j] else last[j]
    have_z = False
    for g in range(G):
        c0 = gptr[g]
        c1 = gptr[g + 1]
        if c1 == c0:
            continue
        ok = True
        for q in range(c0, c1):
            j = gcols[q]
            if not obs[j]:
                ok = False
        if not ok:
            vk[g] = -12 - (1 + (cnt * 7919 + g * 104729) % 61)  # blend.guard.SETTLE + wait
            continue
        if vk[g] >= Kmax:
            vk[g] = -(1 + (cnt * 7919 + g * 104729) % 61)
        if vk[g] < 0:
            vk[g] += 1
            continue
        new = vk[g] == 0
        if new:
            for q in range(c0, c1):
                j = gcols[q]
                vh[j] = h[j]
                vv[j] = min(max(vgap[j] * vgain[j], -vcap[j]), vcap[j])  # vgap: the velocity a gap uses
        vk[g] += 1
        kk = vk[g]
        b0 = gbin[kk]
        if b0 < 0:
            continue
        t = kk / fps
        cv = _knot(wv, g, t, knots) * (d * (1.0 - d ** kk) / (1.0 - d)) + _knot(wl, g, t, knots) * (d2 * (1.0 - d2 ** kk) / (1.0 - d2))
        for q in range(c0, c1):
            Qb[gcols[q]] = 0.0
        si = gsh[g]
        if si >= 0:
            if not have_z:
                _features_all(x, ri, mean, mu, Ls, hist, pos, zf)
                have_z = True
            rho = _rho(ER, EH, NE, g, gate_n0)
            gate = 1.0 / (1.0 + (rho / gate_rho) ** 2)
            weak = 1.0 / (1.0 + (rho / gate_weak) ** 2)
            wq = _knot(wr, g, t, knots) * weak + _knot(wg, g, t, knots) * gate
            for i in range(sh_nm[si]):
                mi = sh_m[si, i]
                r = 0.0
                for qq in range(sh_nO[si]):
                    r += sh_B[si, i, qq] * zf[sh_O[si, qq]]
                r += mu[mi]
                c = ri[mi]
                if new:
                    voff[c] = _wrap(vh[c] - (mean[c] + r))
                Qb[c] = wq * _wrap(mean[c] + r + voff[c] * a ** kk - vh[c])
        pp = 0.0
        pq = 0.0
        qq2 = 0.0
        yp = 0.0
        yq = 0.0
        for q in range(c0, c1):
            j = gcols[q]
            y = f[j] - vh[j]
            if ang[j]:
                y = _wrap(y)
            P = vv[j] * cv
            Qj = Qb[j]
            pp += P * P
            pq += P * Qj
            qq2 += Qj * Qj
            yp += y * P
            yq += y * Qj
        GS[g, b0, 0] += pp
        GS[g, b0, 1] += pq
        GS[g, b0, 2] += qq2
        GS[g, b0, 3] += yp
        GS[g, b0, 4] += yq
        GS[g, b0, 5] += 1.0


@jit
def _shrunk(v, q, beta, c):
    """blend.state.shrunk for one channel."""
    if c <= 0.0:
        return v
    den = v * v + c * (beta * beta * q / (3.0 * (2.0 - beta)))
    return v * v * v / den if den > 0.0 else v


@jit
def _guard_solve(GS, n0, mx, L):
    """blend.guard.solve into L (G, B, 2)."""
    for g in range(GS.shape[0]):
        for b in range(GS.shape[1]):
            pp = GS[g, b, 0]
            pq = GS[g, b, 1]
            qq = GS[g, b, 2]
            yp = GS[g, b, 3]
            yq = GS[g, b, 4]
            n = GS[g, b, 5]
            kap = n0 / n if n > 0 else 0.0
            a11 = pp * (1 + kap) + 1e-12
            a22 = qq * (1 + kap) + 1e-12
            b1 = yp + kap * pp
            b2 = yq + kap * qq
            det = a11 * a22 - pq * pq
            if pp > 1e-9 and qq > 1e-9 and det > 1e-12 * a11 * a22:
                lv = (b1 * a22 - b2 * pq) / det
                lr = (a11 * b2 - pq * b1) / det
            else:
                lv = b1 / a11
                lr = b2 / a22
            if not (n > 0 and pp > 1e-9):
                lv = 1.0
            if not (n > 0 and qq > 1e-9):
                lr = 1.0
            L[g, b, 0] = min(max(lv, 0.0), mx)
            L[g, b, 1] = min(max(lr, 0.0), mx)


@jit
def _guard_lambda(L, g, kk, gzf, which):
    """blend.guard.guard_lambda for one channel: part ``which`` (0 velocity, 1 regression)."""
    if gzf.shape[0] == 1:
        return L[g, 0, which]
    i, fr = _hat(gzf, kk)
    return L[g, i, which] * (1.0 - fr) + L[g, i + 1, which] * fr


@jit
def reg_missing(obs, ri, out):
    """``out[r]`` = regression channel r (channel ``ri[r]``) is missing; returns how many are: the
    state's ``~obs[ri]`` and its ``any()`` in one compiled call (no arrays made)."""
    n = 0
    for r in range(ri.shape[0]):
        miss = not obs[ri[r]]
        out[r] = miss
        n += miss
    return n


@jit
def step_kernel(f, obs, ang, group, mean, std0, ri, mu, knots, wv, wl, wr, wg, sc, par, Ls, vcap, betas, vgain, mm, O, B, has_reg, changed,
                last, h, vel, vn, v0, k, R, off, amean, avar, lstd, hist, sv, out, std, Rv,
                sh_g, sh_m, sh_nm, sh_O, sh_nO, sh_B, ER, EH, NE, gz, gzf, gpar, gcols, gptr, gsh, gpos, vk, vh, vv, voff, GS, GL, gbuf, gbin):
    _beta, d, d2, a, eta, fps, amp_floor, cal_prior, cal_decay = (par[0], par[1], par[2], par[3], par[4], par[5],
                                                                 par[6], par[7], par[8])
    gate_rho, gate_decay, gate_weak, gate_n0, shrink = par[9], par[10], par[11], par[12], par[13]
    C = f.shape[0]
    n = hist.shape[0]
    pos = int(sv[3])
    seen = sv[2] > 0.0
    Rn = ri.shape[0]
    if not seen:
        for j in range(C):
            if obs[j]:
                for rr in range(n):
                    hist[rr, j] = f[j]
    Lm = 0
    for b in range(Ls.shape[0]):
        Lm = max(Lm, Ls[b])
    # the shadow check: one observed regression group predicted from the others
    G = sh_g.shape[0]
    cnt = int(sv[4])
    if G > 0:
        sv[4] += 1
    if G > 0 and cnt > Lm:
        q = cnt % G
        nm = sh_nm[q]
        allobs = True
        for i in range(nm):
            if not obs[ri[sh_m[q, i]]]:
                allobs = False
        if allobs:
            nO = sh_nO[q]
            z = np.empty(nO)
            for qq in range(nO):
                o = sh_O[q, qq]
                b = o // Rn
                c = ri[o % Rn]
                x = f[c] if obs[c] else last[c]
                if b == 0:
                    v = x - mean[c]
                else:
                    v = x - hist[(pos - Ls[b - 1] + 1 + n) % n, c]
                z[qq] = _wrap(v) - mu[o]
            eR = 0.0
            eH = 0.0
            for i in range(nm):
                mi = sh_m[q, i]
                c = ri[mi]
                r = 0.0
                for qq in range(nO):
                    r += sh_B[q, i, qq] * z[qq]
                r += mu[mi]
                e = _wrap(f[c] - mean[c] - r)
                eR += e * e
                e = _wrap(f[c] - hist[(pos - Lm + 1 + n) % n, c])
                eH += e * e
            g = sh_g[q]
            ER[g] = gate_decay * ER[g] + eR
            EH[g] = gate_decay * EH[g] + eH
            NE[g] = min(NE[g] + 1.0, gate_n0)
    guard_on = gpar[3] > 0.0
    if guard_on:
        _guard_update(f, obs, last, ang, group, mean, ri, mu, Ls, hist, pos, knots, wv, wl, wr, wg, d, d2, a, fps, vcap, vgain,
                      h, vn[1], k, gz, gzf, gpar, gcols, gptr, gsh, gpos, vk, vh, vv, voff, GS, sv, sh_m, sh_nm, sh_O, sh_nO, sh_B,
                      ER, EH, NE, gate_rho, gate_weak, gate_n0, Lm, gbuf, gbin)
    anyobs = False
    anymiss = False
    for j in range(C):
        if obs[j]:
            anyobs = True
        else:
            anymiss = True
    if anyobs:
        nback = 0
        zsum = 0.0
        for j in range(C):
            if not obs[j]:
                continue
            if k[j] == 0 and seen:
                dx = f[j] - h[j]
                if ang[j]:
                    dx = _wrap(dx)
                if shrink > 0.0:  # (the jitter's estimate, read only by vel_shrink)
                    p2 = vn[2, j]
                    if p2 == p2:  # the frame before was a difference too: the second difference
                        dd = dx - p2  # (not d2: that is the slower damping)
                        vn[0, j] = (1 - eta) * vn[0, j] + eta * dd * dd
                    vn[2, j] = dx
                vel[j] = vel[j] + betas[j] * (dx - vel[j])
                vn[1, j] = _shrunk(vel[j], vn[0, j], betas[j], shrink)
            else:
                vn[2, j] = np.nan
            da = f[j] - amean[j]
            if ang[j]:
                da = _wrap(da)
            amean[j] = amean[j] + eta * da
            avar[j] = (1 - eta) * avar[j] + eta * da * da
            h[j] = f[j]
            if k[j] > 0:
                e = f[j] - last[j]
                if ang[j]:
                    e = _wrap(e)
                z = e / max(lstd[j], 1e-9)
                zsum += min(z * z, 25.0)
                nback += 1
        if nback:
            lam = cal_decay ** nback
            sv[0] = lam * sv[0] + zsum
            sv[1] = lam * sv[1] + nback
        seen = True
    for j in range(C):
        out[j] = f[j] if obs[j] else 0.0
        std[j] = 0.0
    if anymiss:
        for j in range(C):
            if obs[j]:
                k[j] = 0
            else:
                if k[j] == 0:
                    v0[j] = min(max(vn[1, j] * vgain[j], -vcap[j]), vcap[j])
                    R[j] = h[j]
                k[j] += 1
                Rv[j] = h[j]
        if has_reg:
            nO = O.shape[0]
            z = np.empty(nO)
            zp = np.empty(nO)
            for q in range(nO):
                o = O[q]
                b = o // Rn
                c = ri[o % Rn]
                x = f[c] if obs[c] else last[c]
                xp = hist[pos, c]
                if b == 0:
                    v = x - mean[c]
                    vp = xp - mean[c]
                else:
                    L = Ls[b - 1]
                    v = x - hist[(pos - L + 1 + n) % n, c]
                    vp = xp - hist[(pos - L + n) % n, c]
                z[q] = _wrap(v) - mu[o]
                zp[q] = _wrap(vp) - mu[o]
            for i in range(mm.shape[0]):
                r = 0.0
                for q in range(nO):
                    r += B[i, q] * z[q]
                r += mu[mm[i]]
                c = ri[mm[i]]
                if changed:
                    rp = 0.0
                    for q in range(nO):
                        rp += B[i, q] * zp[q]
                    off[c] = _wrap(R[c] - (mean[c] + (rp + mu[mm[i]])))  # the short way round (an angle)
                off[c] *= a
                val = mean[c] + r + off[c]
                R[c] = val
                Rv[c] = h[c] + _wrap(val - h[c])  # R on the branch of the last value: never 360 away
        L = GL
        if guard_on:
            _guard_solve(GS, gpar[1], gpar[2], L)
        scale = 1.0
        if sv[1] != 0.0:
            scale = min(max(np.sqrt((cal_prior + sv[0]) / (cal_prior + sv[1])), 0.33), 3.0)
        for j in range(C):
            if obs[j]:
                continue
            kk = k[j]
            H = h[j]
            V = H + v0[j] * (d * (1.0 - d ** kk) / (1.0 - d))
            W = H + v0[j] * (d2 * (1.0 - d2 ** kk) / (1.0 - d2))
            t = kk / fps
            g = group[j]
            rho = _rho(ER, EH, NE, g, gate_n0)
            gate = 1.0 / (1.0 + (rho / gate_rho) ** 2)
            weak = 1.0 / (1.0 + (rho / gate_weak) ** 2)
            wrj = _knot(wr, g, t, knots) * weak + _knot(wg, g, t, knots) * gate
            lv = 1.0
            lr = 1.0
            if guard_on:
                lv = _guard_lambda(L, g, float(kk), gzf, 0)
                lr = _guard_lambda(L, g, float(kk), gzf, 1)
            out[j] = H + lv * (_knot(wv, g, t, knots) * (V - H) + _knot(wl, g, t, knots) * (W - H)) + lr * wrj * (Rv[j] - H)
            amp = np.sqrt(avar[j] + (amp_floor * std0[j]) ** 2)
            std[j] = _knot(sc, g, t, knots) * amp * scale
    else:
        for j in range(C):
            k[j] = 0
    pos = (pos + 1) % n
    for j in range(C):
        hist[pos, j] = out[j]
        last[j] = out[j]
        lstd[j] = std[j]
    sv[2] = 1.0 if seen else 0.0
    sv[3] = pos
