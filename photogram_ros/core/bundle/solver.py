"""Levenberg-Marquardt with the Schur complement on points, vectorised over observations.

Per Jacobian evaluation the normal equations are accumulated from per-observation blocks
A_i (2 x m: pose 6 + free intrinsics) and B_i (2 x 3) with bincount over index keys whose
structure is computed once per problem. Points are eliminated with batched 3x3 inverses; the
reduced camera system S = U - W V^-1 W^T is a scipy.sparse product and is solved with a dense
Cholesky when small (the usual case: C*6 of a few hundred), SuperLU otherwise. The damping is
Ceres's: mu * clip(diag(J^T J), 1e-6, 1e32), with the trust-region update of Nielsen/Ceres.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg
from scipy.spatial.transform import Rotation

from photogram_ros.core.bundle import losses


def _cross_cols(M, v):
    """M @ [v]x for M (n, k, 3), v (n, 3)."""
    out = np.empty(M.shape[:-1] + (3,))
    v1, v2, v3 = v[:, None, 0], v[:, None, 1], v[:, None, 2]
    out[..., 0] = M[..., 1] * v3 - M[..., 2] * v2
    out[..., 1] = M[..., 2] * v1 - M[..., 0] * v3
    out[..., 2] = M[..., 0] * v2 - M[..., 1] * v1
    return out


def _inv3(M):
    """Inverses of (n, 3, 3) matrices by their cofactors: the point blocks V (symmetric, damped, positive) are
    inverted this way five times faster than numpy's per-matrix LAPACK calls; a singular block gives non-finite
    values, which the caller's finiteness check turns into a failed step, as LAPACK's error would."""
    a, b, c = M[:, 0, 0], M[:, 0, 1], M[:, 0, 2]
    d, e, f = M[:, 1, 0], M[:, 1, 1], M[:, 1, 2]
    g, h, i = M[:, 2, 0], M[:, 2, 1], M[:, 2, 2]
    out = np.empty_like(M)
    out[:, 0, 0] = e * i - f * h
    out[:, 0, 1] = c * h - b * i
    out[:, 0, 2] = b * f - c * e
    out[:, 1, 0] = f * g - d * i
    out[:, 1, 1] = a * i - c * g
    out[:, 1, 2] = c * d - a * f
    out[:, 2, 0] = d * h - e * g
    out[:, 2, 1] = b * g - a * h
    out[:, 2, 2] = a * e - b * d
    det = a * out[:, 0, 0] + b * out[:, 1, 0] + c * out[:, 2, 0]
    with np.errstate(divide='ignore', invalid='ignore'):
        out /= det[:, None, None]
    return out


def _skew(v):
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], -1), np.stack([v[:, 2], z, -v[:, 0]], -1),
                     np.stack([-v[:, 1], v[:, 0], z], -1)], axis=1)


def _so3_left_jac_inv(phi):
    th = np.linalg.norm(phi, axis=1)
    K = _skew(phi)
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    c = np.where(small, 1.0 / 12.0, 1.0 / ths ** 2 - (1.0 + np.cos(ths)) / (2.0 * ths * np.sin(ths)))
    return np.eye(3) - 0.5 * K + c[:, None, None] * (K @ K)


# Above these the dense Schur complement from observation pairs costs more memory (pairs x 2 x 27
# doubles) or Python loop time (one GEMM per block) than the 3x3-block sparse product.
_MAX_PAIRS = 600_000
_MAX_SEGMENTS = 20_000
_CHUNK_PAIRS = 4096
# Below this many camera unknowns (about 20 free cameras: a sliding window) the reduced system is tiny
# and sorting the observation pairs costs more than it saves (window update 81 -> 102 ms median).
_MIN_CAMERA_UNKNOWNS_FOR_PAIRS = 120


class _Structure:
    """Index bookkeeping that does not change between iterations.

    The camera-side unknowns are laid out in chunks of 3 (pose = 2 chunks, the free intrinsics of a
    group padded to a multiple of 3) so that W = J_c^T J_p is a block-sparse matrix of 3x3 blocks,
    whose products scipy runs about twice as fast as scalar CSR.
    """

    def __init__(self, d, sel, dense_limit, gnss_bias: bool = False, gnss_tilt: bool = False):
        C, P = len(d['R']), len(d['X'])
        self.kf = sel.shape[1]
        self.kf3 = -(-self.kf // 3) * 3
        free_c = ~d['fixed_cams']
        self.cam_col = np.full(C, -1, np.int64)
        self.cam_col[free_c] = 6 * np.arange(free_c.sum())
        n_pose = 6 * int(free_c.sum())
        G = len(d['intr'])
        self.intr_col = n_pose + self.kf3 * np.arange(G)
        self.nc = n_pose + self.kf3 * G
        # The GNSS bias (3 unknowns, ENU m) comes after the intrinsics: a chunk of 3 that no observation touches;
        # with the tilt, a second chunk holds its 2 slopes (and one unused column).
        self.bias_col = -1
        self.n_bias = 0          # the bias's unknowns: 3, or 5 with the tilt
        self.bias_width = 0      # their columns, padded to chunks of 3
        if gnss_bias and 'gnss_cam' in d:
            self.bias_col = self.nc
            self.n_bias = 5 if gnss_tilt else 3
            self.bias_width = -(-self.n_bias // 3) * 3
            self.nc += self.bias_width
        real = np.ones(self.nc, bool)
        for k in range(self.kf, self.kf3):
            real[self.intr_col + k] = False
        real[self.bias_col + self.n_bias:self.bias_col + self.bias_width] = False
        self.real = real
        self.trash = self.nc
        free_p = ~d['fixed_points']
        self.pt_col = np.full(P, -1, np.int64)
        self.pt_col[free_p] = np.arange(free_p.sum())
        self.npf = int(free_p.sum())
        oc, op = d['obs_cam'], d['obs_pt']
        cc = self.cam_col[oc]
        pose_idx = np.where(cc[:, None] >= 0, cc[:, None] + np.arange(6), self.trash)
        intr_idx = self.intr_col[d['group'][oc]][:, None] + np.arange(self.kf3)
        self.idx = np.concatenate([pose_idx, intr_idx], axis=1)     # (N, m)
        self.m = self.idx.shape[1]
        n1 = self.nc + 1
        # All m x m entries of one observation land in the block of its (camera, intrinsics group)
        # pair: sum observations per pair with one sparse product, then scatter the few pair blocks.
        pair_key = oc * G + d['group'][oc]
        upair, pair_inv = np.unique(pair_key, return_inverse=True)
        N = len(oc)
        # Observations grouped by pair: each pair's U block is one GEMM over a contiguous slice.
        self.pair_order = np.argsort(pair_inv, kind='stable')
        self.pair_bounds = np.concatenate([[0], np.cumsum(np.bincount(pair_inv, minlength=len(upair)))]).tolist()
        first = np.zeros(len(upair), np.int64)
        first[pair_inv[::-1]] = np.arange(N)[::-1]
        self.pair_idx = self.idx[first]                            # (pairs, m)
        keys = [(self.pair_idx[:, :, None] * n1 + self.pair_idx[:, None, :]).ravel()]
        self.prior_idx = {}
        for name in ('gnss_cam', 'att_cam'):
            if name in d:
                c = self.cam_col[d[name]]
                pidx = np.where(c[:, None] >= 0, c[:, None] + np.arange(6), self.trash)
                if name == 'gnss_cam' and self.bias_col >= 0:
                    w = self.bias_width
                    pidx = np.concatenate([pidx, np.broadcast_to(self.bias_col + np.arange(w), (len(c), w))], axis=1)
                self.prior_idx[name] = pidx
                keys.append((pidx[:, :, None] * n1 + pidx[:, None, :]).ravel())
        ukeys, self.u_inv = np.unique(np.concatenate(keys), return_inverse=True)
        self.nu = len(ukeys)
        rows, cols = ukeys // n1, ukeys % n1
        self.u_keep = (rows < self.nc) & (cols < self.nc)
        self.u_rows, self.u_cols = rows[self.u_keep], cols[self.u_keep]
        # W blocks: one 3x3 block per (3-row chunk of camera-side unknowns, free point).
        ptc = self.pt_col[op]
        self.obs_ptc = ptc
        nrb = self.nc // 3
        self.nrb = nrb
        rb = self.idx[:, ::3] // 3                                  # (N, m/3)
        valid = (rb < nrb) & (ptc[:, None] >= 0)
        self.w_valid = valid.ravel()
        npf1 = max(self.npf, 1)
        wkeys = (rb * npf1 + np.maximum(ptc, 0)[:, None]).ravel()[self.w_valid]
        uw, inv = np.unique(wkeys, return_inverse=True)
        self.nw = len(uw)
        self.w_sum = sp.csr_matrix((np.ones(len(inv)), (inv, np.arange(len(inv)))), shape=(self.nw, len(inv)))
        w_rows = uw // npf1
        self.w_pt = uw % npf1
        self.w_indptr = np.concatenate([[0], np.cumsum(np.bincount(w_rows, minlength=nrb))])
        # The transpose, blocks ordered by point.
        self.wt_perm = np.lexsort((w_rows, self.w_pt))
        self.wt_indices = w_rows[self.wt_perm]
        self.wt_indptr = np.concatenate([[0], np.cumsum(np.bincount(self.w_pt, minlength=self.npf))])
        vo = ptc >= 0
        self.pt_sum = sp.csr_matrix((np.ones(vo.sum()), (ptc[vo], np.nonzero(vo)[0])), shape=(self.npf, N))
        self.pairs = (self._observation_pairs(pair_inv, vo)
                      if _MIN_CAMERA_UNKNOWNS_FOR_PAIRS <= self.nc <= dense_limit else None)

    def _observation_pairs(self, pair_inv, vo):
        """Segments of observation pairs for the dense Schur complement, or None if too many.

        S = U - sum_points sum_{i,j observe it} W_i V^-1 W_j^T, and each (i, j) product lands in the
        block of (camera-group pair of i, that of j). Sorting the pairs by block once per problem
        turns every block into one small GEMM over a contiguous slice (only blocks a <= b: S is
        symmetric), which beats scipy's scalar 3x3-block sparse product by about 3x.
        """
        obs = np.nonzero(vo)[0]
        pt = self.obs_ptc[obs]
        order = np.argsort(pt, kind='stable')
        deg = np.bincount(pt, minlength=self.npf)
        n_pairs = int(np.sum(deg.astype(np.int64) ** 2))
        if n_pairs > _MAX_PAIRS:
            return None
        start = np.concatenate([[0], np.cumsum(deg)[:-1]])
        pts = pt[order]
        rep = deg[pts]
        i_s = np.repeat(np.arange(len(obs)), rep)
        within = np.arange(n_pairs) - np.repeat(np.cumsum(rep) - rep, rep)
        j_s = start[pts[i_s]] + within
        I, J = order[i_s], order[j_s]                    # indices into obs
        ka, kb = pair_inv[obs[I]], pair_inv[obs[J]]
        keep = ka <= kb
        I, J, ka, kb = I[keep], J[keep], ka[keep], kb[keep]
        srt = np.lexsort((kb, ka))
        I, J, ka, kb = I[srt], J[srt], ka[srt], kb[srt]
        new = np.concatenate([[True], (ka[1:] != ka[:-1]) | (kb[1:] != kb[:-1])])
        bounds = np.concatenate([np.nonzero(new)[0], [len(ka)]])
        if len(bounds) - 1 > _MAX_SEGMENTS:
            return None
        sa, sb = ka[new], kb[new]
        n1 = self.nc + 1
        ra, rb = self.pair_idx[sa], self.pair_idx[sb]             # (segments, m)
        flat_ab = (ra[:, :, None] * n1 + rb[:, None, :]).ravel()
        off = sa != sb                                             # mirrored blocks
        flat_ba = (rb[off][:, None, :] * n1 + ra[off][:, :, None]).ravel()
        chunks, slo = [], 0
        for s in range(1, len(bounds)):
            if bounds[s] - bounds[slo] >= _CHUNK_PAIRS or s == len(bounds) - 1:
                chunks.append((int(bounds[slo]), int(bounds[s]), slo, s))
                slo = s
        cap = max(hi - lo for lo, hi, _, _ in chunks) if chunks else 0
        return dict(obs=obs, I=I, J=J, bounds=bounds.tolist(), flat=np.concatenate([flat_ab, flat_ba]),
                    off=off, chunks=chunks, chunk_cap=cap)


class Solver:
    def __init__(self, d, options):
        self.d = d
        self.o = options
        self.sel = d['model'].selector(options.refine_intrinsics)
        self.st = _Structure(d, self.sel, options.dense_limit, gnss_bias=options.estimate_gnss_bias,
                             gnss_tilt=options.estimate_gnss_bias and options.estimate_gnss_tilt)
        if self.st.n_bias == 5:
            # The tilt's lever: each fix's horizontal offset from the fixes' centre (or the one given), m.
            gp = d['gnss_pos'][:, :2]
            centre = gp.mean(axis=0) if d.get('gnss_tilt_centre') is None else d['gnss_tilt_centre']
            self.tilt_arm = gp - centre

    # --- residuals --------------------------------------------------------------------------

    def _reproj(self, R, t, X, intr, jac):
        d = self.d
        oc, op = d['obs_cam'], d['obs_pt']
        Rc = R[oc]
        RX = np.einsum('nij,nj->ni', Rc, X[op])
        uv, Jp, Jk = d['model'].project(RX + t[oc], intr[d['group'][oc]], jac)
        r = uv - d['obs_uv']
        return r, RX, Rc, Jp, Jk

    def cost_parts(self, R, t, X, intr, b):
        d = self.d
        r = self._reproj(R, t, X, intr, False)[0]
        s = np.einsum('ni,ni->n', r, r)
        rho, _ = losses.evaluate(self.o.loss, s, d.get('obs_scale', self.o.loss_scale_px))
        parts = {'reprojection': 0.5 * float(rho.sum())}
        if 'gnss_cam' in d:
            e = self._gnss_err(R, t, b)
            rw = np.einsum('mij,mj->mi', d['gnss_W'], e)
            parts['gnss'] = 0.5 * float(np.sum(rw * rw))
        if 'pp_idx' in d:
            rp = (X[d['pp_idx']] - d['pp_pos']) / d['pp_sigma']
            parts['gcp'] = 0.5 * float(np.sum(rp * rp))
        if 'att_cam' in d:
            phi = self._att_err(R)
            parts['attitude'] = 0.5 * float(np.sum((phi / d['att_sigma']) ** 2))
        return parts

    def _gnss_err(self, R, t, b):
        """Antenna minus fix adjusted (gnss_pos - b, b the GNSS bias: zero unless estimated; with the tilt, the
        fix's height also less b[3:5] . its horizontal offset from the centre), (M, 3) m."""
        d = self.d
        c = d['gnss_cam']
        v = d['lever'][None, :] - t[c]
        e = np.einsum('mji,mj->mi', R[c], v) - d['gnss_pos'] + b[:3]
        if self.st.n_bias == 5:
            e[:, 2] += self.tilt_arm @ b[3:5]
        return e

    def _att_err(self, R):
        d = self.d
        E = R[d['att_cam']] @ np.transpose(d['att_R'], (0, 2, 1))
        return Rotation.from_matrix(E).as_rotvec()

    def linearise(self, R, t, X, intr, b):
        """Normal-equation pieces at the current estimate."""
        d, st = self.d, self.st
        r, RX, Rc, Jp, Jk = self._reproj(R, t, X, intr, True)
        s = np.einsum('ni,ni->n', r, r)
        _, d1 = losses.evaluate(self.o.loss, s, d.get('obs_scale', self.o.loss_scale_px))
        w = np.sqrt(d1)[:, None]
        n, m = len(r), st.m
        A = np.zeros((n, 2, m))
        A[:, :, :3] = -_cross_cols(Jp, RX)
        A[:, :, 3:6] = Jp
        if st.kf:
            A[:, :, 6:6 + st.kf] = (Jk.reshape(-1, Jk.shape[2]) @ self.sel).reshape(n, 2, st.kf)
        B = Jp @ Rc
        if self.o.loss != 'linear':
            r = r * w
            A *= w[:, :, None]
            B *= w[:, :, None]
        nc1 = st.nc + 1
        # U and g_c per (camera, intrinsics group) pair: one GEMM each over the pair's observations
        # (numpy's batched 2 x m products per observation are ten times slower).
        Ao = A[st.pair_order]
        pb = st.pair_bounds
        ublk = np.empty((len(pb) - 1, m, m))
        for k in range(len(pb) - 1):
            a = Ao[pb[k]:pb[k + 1]].reshape(-1, m)
            np.matmul(a.T, a, out=ublk[k])
        u_vals = [ublk.ravel()]
        # Sums in a fixed order (elementwise, then bincount): SIMD reductions peel by memory alignment,
        # and the incremental AT promises bit-identical results whatever its arrays' layout.
        g_obs = A[:, 0, :] * r[:, 0:1] + A[:, 1, :] * r[:, 1:2]
        gc = np.bincount(st.idx.ravel(), g_obs.ravel(), minlength=nc1)
        if 'gnss_cam' in d:
            c = d['gnss_cam']
            v = d['lever'][None, :] - t[c]
            RT = np.transpose(R[c], (0, 2, 1))
            J = np.concatenate([_cross_cols(RT, v), -RT], axis=2)
            if st.bias_col >= 0:
                J = np.concatenate([J, np.broadcast_to(np.eye(3), (len(c), 3, 3))], axis=2)
            if st.n_bias == 5:
                Jt = np.zeros((len(c), 3, 3))
                Jt[:, 2, :2] = self.tilt_arm
                J = np.concatenate([J, Jt], axis=2)
            J = d['gnss_W'] @ J
            rg = np.einsum('mij,mj->mi', d['gnss_W'], self._gnss_err(R, t, b))
            u_vals.append(np.einsum('mka,mkb->mab', J, J).ravel())
            gc += np.bincount(st.prior_idx['gnss_cam'].ravel(), np.einsum('mka,mk->ma', J, rg).ravel(),
                              minlength=nc1)
        if 'att_cam' in d:
            phi = self._att_err(R)
            J = _so3_left_jac_inv(phi) / d['att_sigma'][:, :, None]
            J = np.concatenate([J, np.zeros_like(J)], axis=2)
            ra = phi / d['att_sigma']
            u_vals.append(np.einsum('mka,mkb->mab', J, J).ravel())
            gc += np.bincount(st.prior_idx['att_cam'].ravel(), np.einsum('mka,mk->ma', J, ra).ravel(),
                              minlength=nc1)
        u = np.bincount(st.u_inv, np.concatenate(u_vals), minlength=st.nu)[st.u_keep]
        npf = st.npf
        Bt = np.ascontiguousarray(B.transpose(0, 2, 1))
        V = (st.pt_sum @ (Bt @ B).reshape(-1, 9)).reshape(npf, 3, 3)
        gp = st.pt_sum @ (Bt @ r[:, :, None]).reshape(-1, 3)
        if 'pp_idx' in d:
            pc = st.pt_col[d['pp_idx']]
            ok = pc >= 0
            iw = 1.0 / d['pp_sigma'][ok]
            rp = (X[d['pp_idx'][ok]] - d['pp_pos'][ok]) * iw
            np.add.at(V, (pc[ok][:, None], np.arange(3)[None, :], np.arange(3)[None, :]), iw * iw)
            np.add.at(gp, pc[ok], rp * iw)
        Et = Bt @ A                                       # (N, 3, m): W_i^T per observation
        U = sp.csr_matrix((u, (st.u_rows, st.u_cols)), shape=(st.nc, st.nc))
        return dict(U=U, Ud=U.diagonal(), gc=gc[:st.nc], V=V, gp=gp, Et=Et)

    def _Wd(self, lin):
        """The 3x3 blocks of W = J_c^T J_p (summed over observations sharing a block), cached."""
        if 'Wd' not in lin:
            st = self.st
            E = np.ascontiguousarray(lin['Et'].transpose(0, 2, 1)).reshape(-1, 9)[st.w_valid]
            lin['Wd'] = (st.w_sum @ E).reshape(-1, 3, 3)
        return lin['Wd']

    # --- linear algebra --------------------------------------------------------------------

    def _W(self, blocks):
        st = self.st
        return sp.bsr_matrix((blocks, st.w_pt, st.w_indptr),
                             shape=(st.nc, 3 * st.npf), blocksize=(3, 3))

    def _WT(self, blocks):
        st = self.st
        return sp.bsr_matrix((blocks[st.wt_perm].transpose(0, 2, 1), st.wt_indices, st.wt_indptr),
                             shape=(3 * st.npf, st.nc), blocksize=(3, 3))

    def solve_step(self, lin, mu):
        st = self.st
        Dc = np.clip(lin['Ud'], 1e-6, 1e32)
        Vdiag = np.clip(np.diagonal(lin['V'], axis1=1, axis2=2), 1e-6, 1e32)
        Vd = lin['V'] + mu * Vdiag[:, :, None] * np.eye(3)
        Vinv = _inv3(Vd)
        gp = lin['gp']
        real = st.real
        dc = np.zeros(st.nc)
        if st.pairs is not None:
            S, rhs, wt_dc = self._schur_pairs(lin, Vinv)
        else:
            Wd = self._Wd(lin)
            WT = self._WT(Wd)
            WV = self._W(Wd @ Vinv[st.w_pt])
            rhs = -lin['gc'] + WV @ gp.ravel()
            wt_dc = lambda x: (WT @ x).reshape(-1, 3)  # noqa: E731
        if not real.any():
            pass
        elif st.nc <= self.o.dense_limit:
            if st.pairs is None:
                S = lin['U'].toarray() - (WV @ WT).toarray()
            S[np.diag_indices_from(S)] += mu * Dc
            if not real.all():
                S = S[np.ix_(real, real)]
            try:
                dc[real] = scipy.linalg.cho_solve(scipy.linalg.cho_factor(S, check_finite=False), rhs[real],
                                                  check_finite=False)
            except (np.linalg.LinAlgError, ValueError):
                return None
        else:
            S = (lin['U'] - WV @ WT + sp.diags(mu * Dc)).tocsc()[real][:, real]
            try:
                dc[real] = scipy.sparse.linalg.splu(S.tocsc()).solve(rhs[real])
            except RuntimeError:
                return None
        dp = -(Vinv @ (gp + wt_dc(dc))[:, :, None])[:, :, 0]
        if not (np.all(np.isfinite(dc)) and np.all(np.isfinite(dp))):
            return None
        g_dot = float(lin['gc'] @ dc + np.sum(gp * dp))
        d_dot = float(np.sum(Dc * dc * dc) + np.sum(Vdiag * dp * dp))
        pred = -0.5 * g_dot + 0.5 * mu * d_dot
        return dc, dp, pred

    def _schur_pairs(self, lin, Vinv):
        """Dense S = U - W V^-1 W^T, rhs = -g_c + W V^-1 g_p and dc -> W^T dc, per observation."""
        st, pr = self.st, self.st.pairs
        obs = pr['obs']
        Et = lin['Et'][obs]                                   # (Nv, 3, m)
        ptc = st.obs_ptc[obs]
        Yt = Vinv[ptc] @ Et                                   # (V^-1 W_i^T), V symmetric
        m = Et.shape[2]
        b = pr['bounds']
        blocks = np.empty((len(b) - 1, m, m))
        I, J = pr['I'], pr['J']
        cap = pr['chunk_cap']
        bufa, bufb = np.empty((cap, 3, m)), np.empty((cap, 3, m))
        # Gather a cache-sized chunk of pairs at a time: the whole gather is tens of MB, and on a
        # busy machine memory bandwidth, not the GEMMs, is what it costs.
        for plo, phi, slo, shi in pr['chunks']:
            xa = np.take(Yt, I[plo:phi], axis=0, out=bufa[:phi - plo])
            xb = np.take(Et, J[plo:phi], axis=0, out=bufb[:phi - plo])
            for s in range(slo, shi):
                lo, hi = b[s] - plo, b[s + 1] - plo
                np.matmul(xa[lo:hi].reshape(-1, m).T, xb[lo:hi].reshape(-1, m), out=blocks[s])
        vals = np.concatenate([blocks.ravel(), blocks[pr['off']].ravel()])
        n1 = st.nc + 1
        S = lin['U'].toarray()
        S -= np.bincount(pr['flat'], vals, minlength=n1 * n1).reshape(n1, n1)[:st.nc, :st.nc]
        idx = st.idx[obs]
        g = lin['gp'][ptc]
        yg = Yt[:, 0, :] * g[:, 0:1] + Yt[:, 1, :] * g[:, 1:2] + Yt[:, 2, :] * g[:, 2:3]
        rhs = -lin['gc'] + np.bincount(idx.ravel(), yg.ravel(), minlength=n1)[:st.nc]

        def wt_dc(dc):
            dcx = np.append(dc, 0.0)[idx]                     # (Nv, m)
            acc = Et[:, :, 0] * dcx[:, 0:1]
            for j in range(1, m):
                acc += Et[:, :, j] * dcx[:, j:j + 1]
            return np.stack([np.bincount(ptc, acc[:, k], minlength=st.npf) for k in range(3)], axis=1)
        return S, rhs, wt_dc

    def apply(self, R, t, X, intr, b, dc, dp):
        st = self.st
        R, t, X, intr = R.copy(), t.copy(), X.copy(), intr.copy()
        if st.bias_col >= 0:
            b = b + dc[st.bias_col:st.bias_col + st.n_bias]
        free = st.cam_col >= 0
        if free.any():
            dpose = dc[st.cam_col[free][:, None] + np.arange(6)]
            R[free] = Rotation.from_rotvec(dpose[:, :3]).as_matrix() @ R[free]
            t[free] += dpose[:, 3:]
        if st.kf:
            dk = dc[st.intr_col[:, None] + np.arange(st.kf)]
            intr += dk @ self.sel.T
        X[st.pt_col >= 0] += dp
        return R, t, X, intr, b

    # --- the loop -------------------------------------------------------------------------

    def run(self):
        o, d = self.o, self.d
        R, t, X, intr, b = d['R'], d['t'], d['X'], d['intr'], np.zeros(max(self.st.n_bias, 3))
        t0 = time.perf_counter()
        cost = sum(self.cost_parts(R, t, X, intr, b).values())
        init = cost
        hist = [cost]
        hist_t = [time.perf_counter() - t0]
        if not np.isfinite(cost):
            return dict(status='failed', reason='initial cost is not finite (a point on a camera centre?)',
                        R=R, t=t, X=X, intr=intr, b=b, init=init, cost=cost, iters=0, ok=0, hist=hist, hist_t=hist_t,
                        seconds=time.perf_counter() - t0, lin=None)
        radius, nu = float(o.initial_trust_radius), 2.0
        status, reason, iters, ok = 'max_iterations', f'stopped after {o.max_iterations} iterations', 0, 0
        lin = self.linearise(R, t, X, intr, b)
        while iters < o.max_iterations:
            gmax = max(np.abs(lin['gc']).max(initial=0.0), np.abs(lin['gp']).max(initial=0.0))
            if gmax <= o.gradient_tolerance:
                status, reason = 'converged', 'gradient below tolerance'
                break
            iters += 1
            step = self.solve_step(lin, 1.0 / radius)
            if step is None:
                radius /= nu
                nu *= 2.0
                if radius < 1e-32:
                    status, reason = 'failed', 'linear system could not be solved at any damping'
                    break
                continue
            dc, dp, pred = step
            xnorm = np.sqrt(np.sum(t ** 2) + np.sum(X ** 2))
            snorm = np.sqrt(dc @ dc + np.sum(dp * dp))
            if snorm <= o.parameter_tolerance * (xnorm + o.parameter_tolerance):
                status, reason = 'converged', 'step below parameter tolerance'
                break
            Rn, tn, Xn, kn, bn = self.apply(R, t, X, intr, b, dc, dp)
            new = sum(self.cost_parts(Rn, tn, Xn, kn, bn).values())
            rho = (cost - new) / pred if pred > 0 else -1.0
            if np.isfinite(new) and rho > 1e-3:
                ok += 1
                R, t, X, intr, b = Rn, tn, Xn, kn, bn
                rel = (cost - new) / max(cost, 1e-300)
                cost = new
                hist.append(cost)
                hist_t.append(time.perf_counter() - t0)
                radius = radius / max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                radius = min(radius, 1e16)
                nu = 2.0
                if rel < o.function_tolerance:
                    status, reason = 'converged', 'relative cost decrease below function tolerance'
                    break
                lin = self.linearise(R, t, X, intr, b)
            else:
                radius /= nu
                nu *= 2.0
                if radius < 1e-32:
                    status, reason = 'converged', 'no further decrease possible (trust region collapsed)'
                    break
        return dict(status=status, reason=reason, R=R, t=t, X=X, intr=intr, b=b, init=init, cost=cost,
                    iters=iters, ok=ok, hist=hist, hist_t=hist_t, seconds=time.perf_counter() - t0)

    # --- covariance -----------------------------------------------------------------------

    def variance_factor(self, cost):
        """A-posteriori variance of unit weight: 2 cost / redundancy (None without redundancy)."""
        d, st = self.d, self.st
        n_res = 2 * len(d['obs_cam']) + sum(3 * len(d[k]) for k in ('gnss_cam', 'pp_idx', 'att_cam') if k in d)
        r = n_res - int(st.real.sum()) - 3 * st.npf
        return 2.0 * float(cost) / r if r > 0 else None

    def _reduced_inverse(self, R, t, X, intr, b):
        """(lin, Vinv, Wd, Sc): the inverse Sc of the reduced camera system S = U - W V^-1 W^T (zeros
        on the intrinsics' padding) at the estimate; None when singular (free gauge)."""
        st = self.st
        lin = self.linearise(R, t, X, intr, b)
        V = lin['V']
        try:
            np.linalg.cholesky(V)
            Vinv = np.linalg.inv(V)
        except np.linalg.LinAlgError:
            return None
        Wd = self._Wd(lin)
        WV = self._W(Wd @ Vinv[st.w_pt])
        S = lin['U'].toarray() - (WV @ self._WT(Wd)).toarray()
        real = st.real
        Sc = np.zeros_like(S)
        try:
            if real.any():
                Sr = S[np.ix_(real, real)]
                np.linalg.cholesky(Sr)
                Sc[np.ix_(real, real)] = np.linalg.inv(Sr)
        except np.linalg.LinAlgError:
            return None
        return lin, Vinv, Wd, Sc

    def _centre_jacobian(self, R, t, free):
        """d(camera centre)/d(pose unknowns) of the free cameras: (F, 3, 6)."""
        RT = np.transpose(R[free], (0, 2, 1))
        return np.concatenate([-_cross_cols(RT, t[free]), -RT], axis=2)

    def covariance(self, R, t, X, intr, b, points: bool = True, gnss_bias_free: bool = False):
        """Marginal covariances at the estimate, unscaled (inverse of J^T J at the residuals' weights).

        Returns camera centres (C,3,3), points (P,3,3; None unless `points`), the free intrinsics per group
        (K,kf,kf) and the
        correlation of each free intrinsic with the block's height (K, kf; see `_height_correlation`);
        all None when the system is singular (free gauge). S^-1 of the reduced camera system is the
        marginal covariance of every camera-side unknown, intrinsics included, with the points
        already marginalised by the Schur complement. gnss_bias_free: as if the fixes' constant offset were
        one more unknown (`_free_gnss_bias`), whose (3, 3) covariance comes fifth (else None); all None when
        nothing else (GCPs) then holds the block. A bias the solver estimates (`BundleOptions.estimate_gnss_bias`)
        is an unknown of S already: its covariance is S^-1's.
        """
        st = self.st
        inv = self._reduced_inverse(R, t, X, intr, b)
        if inv is None:
            return None, None, None, None, None
        lin, Vinv, Wd, Sc = inv
        bias_cov = None
        if st.bias_col >= 0:
            ix = st.bias_col + np.arange(3)
            bias_cov = Sc[np.ix_(ix, ix)].copy()
        elif gnss_bias_free and 'gnss_cam' in self.d:
            freed = self._free_gnss_bias(R, t, Sc)
            if freed is None:
                return None, None, None, None, None
            Sc, bias_cov = freed
        W = self._W(Wd)
        C = len(R)
        cam_cov = np.zeros((C, 3, 3))
        free = st.cam_col >= 0
        if free.any():
            ix = st.cam_col[free][:, None] + np.arange(6)
            Spose = Sc[ix[:, :, None], ix[:, None, :]]
            J = self._centre_jacobian(R, t, free)
            cam_cov[free] = J @ Spose @ np.transpose(J, (0, 2, 1))
        pt_cov = self._point_covariance(W, Vinv, Sc, len(X)) if points else None
        intr_cov = corr = None
        if st.kf:
            ix = st.intr_col[:, None] + np.arange(st.kf)
            intr_cov = Sc[ix[:, :, None], ix[:, None, :]]
            corr = self._height_correlation(R, t, Vinv, W, Sc)
        return cam_cov, pt_cov, intr_cov, corr, bias_cov

    def _free_gnss_bias(self, R, t, Sc):
        """(Sc', Cb): Sc with the GNSS bias b (3, ENU m; each fix's residual L_m (antenna_m - fix_m + b)) marginalised as
        one more unknown. The joint information [[S, A], [A^T, M]] with A = sum_m J_m^T L_m (J_m the fix's
        whitened Jacobian in the camera-side unknowns) and M = sum_m L_m^T L_m leaves S - A M^-1 A^T on the camera
        side, whose inverse is Sc + Sc A (M - A^T Sc A)^-1 A^T Sc (Woodbury); Cb = (M - A^T Sc A)^-1 is the
        bias's own (unscaled) covariance. None when M - A^T Sc A is not positive definite: the fixes were all
        that held the block's position."""
        d, st = self.d, self.st
        c = d['gnss_cam']
        cols = st.cam_col[c]
        L = d['gnss_W']
        M = np.einsum('mki,mkj->ij', L, L)
        A = np.zeros((st.nc, 3))
        free = cols >= 0
        if free.any():
            v = d['lever'][None, :] - t[c[free]]
            RT = np.transpose(R[c[free]], (0, 2, 1))
            J = L[free] @ np.concatenate([_cross_cols(RT, v), -RT], axis=2)       # (F, 3, 6)
            JL = np.einsum('mka,mkj->maj', J, L[free])                             # (F, 6, 3)
            np.add.at(A, cols[free][:, None] + np.arange(6), JL)
        SA = Sc @ A
        G = M - A.T @ SA
        try:
            np.linalg.cholesky(G)
        except np.linalg.LinAlgError:
            return None
        Gi = np.linalg.inv(G)
        return Sc + SA @ Gi @ SA.T, Gi

    def _point_covariance(self, W, Vinv, Sc, n_points: int):
        """(P, 3, 3) marginal covariances of the points: V^-1 + V^-1 W^T S^-1 W V^-1 per point."""
        st = self.st
        pt_cov = np.zeros((n_points, 3, 3))
        blocks = np.zeros((st.npf, 3, 3))
        Wc = W.tocsr().tocsc()
        for a in range(0, st.npf, 2000):
            b = min(st.npf, a + 2000)
            Wk = Wc[:, 3 * a:3 * b].toarray()
            Q = Sc @ Wk
            blocks[a:b] = np.einsum('rka,rkb->kab', Wk.reshape(st.nc, b - a, 3), Q.reshape(st.nc, b - a, 3))
        pt_cov[st.pt_col >= 0] = Vinv + Vinv @ blocks @ Vinv
        return pt_cov

    def _height_correlation(self, R, t, Vinv, W, Sc):
        """(K, kf) correlation of each free intrinsic with the block's height H = mean height (map z)
        of the free camera centres minus that of the free points: on a flat nadir block the focal
        length and the ground's depth trade off (|corr| near 1), which the intrinsic's own sigma hides.

        With g = a.c + b.p (c camera-side unknowns, p points) and y = W V^-1 b:
        var(g) = (a - y)^T Sc (a - y) + b^T V^-1 b and cov(e.c, g) = e^T Sc (a - y).
        """
        st = self.st
        free = st.cam_col >= 0
        a = np.zeros(st.nc)
        if free.any():
            J = self._centre_jacobian(R, t, free)                  # (F, 3, 6)
            np.add.at(a, st.cam_col[free][:, None] + np.arange(6), J[:, 2, :] / free.sum())
        bp = np.zeros((st.npf, 3))
        if st.npf:
            bp[:, 2] = -1.0 / st.npf
        vb = np.einsum('pij,pj->pi', Vinv, bp)
        y = W @ vb.ravel()
        ay = a - y
        Say = Sc @ ay
        var_h = float(ay @ Say + np.sum(bp * vb))
        ix = st.intr_col[:, None] + np.arange(st.kf)
        sd = np.sqrt(np.clip(np.diagonal(Sc)[ix], 1e-300, None))
        return Say[ix] / (sd * np.sqrt(max(var_h, 1e-300)))

    def residual_rms(self, R, t, X, intr, b) -> dict:
        """The RMS of each residual kind at (R, t, X, intr, b): reprojection px, GNSS m (None without), GCP m, attitude rad."""
        d = self.d
        rms = {}
        r = self._reproj(R, t, X, intr, False)[0]
        rms['reprojection_px'] = float(np.sqrt(np.mean(np.sum(r * r, axis=1)))) if len(r) else float('nan')
        rms['gnss_m'] = (float(np.sqrt(np.mean(np.sum(self._gnss_err(R, t, b) ** 2, axis=1))))
                         if 'gnss_cam' in d else None)
        rms['gcp_m'] = (float(np.sqrt(np.mean(np.sum((X[d['pp_idx']] - d['pp_pos']) ** 2, axis=1))))
                        if 'pp_idx' in d else None)
        rms['attitude_rad'] = (float(np.sqrt(np.mean(np.sum(self._att_err(R) ** 2, axis=1))))
                               if 'att_cam' in d else None)
        return rms
