"""Compiled CPU kernels of the Gaussian core: the rasterizer's projection, tile layout and compositing
(forward and backward), the HexPlane's sampling and regularisers, the SH colour and the training SSIM.

A CPU training step spent most of its time in passes of PyTorch operations over padded candidate arrays
(``[chunks, pixels, slots]`` in :mod:`.torch_cpu`), in ``grid_sample``'s backward and in the autograd
of small per-Gaussian formulas. The same functions written as loops -- compositing per tile as the
3D-GS rasterizer does (front to back with all of a tile's pixels in vector lanes, stop at the
transmittance floor; backward back to front, recovering the transmittance by division), each Gaussian's
projection and SH with its analytic derivatives -- do one pass over what matters. Each is the same
function of the same inputs as the PyTorch code it stands in for, equal up to float rounding
(``tests/test_rasterize.py``, ``tests/test_native_kernels.py``).

The C source below is compiled on first use with the system C compiler (``cc``, or ``$CC``) into a
shared library under the user's cache folder and loaded with :mod:`ctypes`: no Python or torch headers,
a few seconds to build. Without a compiler (or with ``BENCH4D_NATIVE=0``) :func:`kernels` returns
``None`` and every caller runs its PyTorch code. The source lives in this module so that the code
digests of cache keys follow every change of it.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import torch
from torch import Tensor

HEADER = r"""
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* Pixels are processed in groups of LANES (vector lanes); per-lane partial sums keep reductions in a
 * fixed order, so the results do not depend on the vector width the compiler picks. */
#define LANES 8

/* GCC builds the hot kernels twice, for AVX2 and for the x86-64 baseline, and picks one at load time.
 * With -ffp-contract=off both do the same float operations in the same order: the same numbers. */
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && defined(__linux__)
#define HOT __attribute__((target_clones("avx2", "default")))
#else
#define HOT
#endif
#if defined(__GNUC__)
#define PREFETCH(address) __builtin_prefetch(address)
#else
#define PREFETCH(address) ((void)0)
#endif
#if defined(__GNUC__)
#define NOINLINE HOT __attribute__((noinline))
#else
#define NOINLINE
#endif

static inline int64_t min_i64(int64_t a, int64_t b) { return a < b ? a : b; }

static inline double clamp_d(double x, double lo, double hi) { return x < lo ? lo : (x > hi ? hi : x); }

/* exp(x) in float, within 2 ulp for x in [-87, 88] (clamped outside): range reduction by ln 2 (split in
 * two parts) and a degree-7 polynomial, written so that it vectorises (no libm call). */
static inline float exp_f32(float x) {
    x = x < -87.0f ? -87.0f : x;
    x = x > 88.0f ? 88.0f : x;
    float t = x * 1.44269504088896341f + 12582912.0f;  /* adding 1.5 * 2^23 rounds to an integer */
    float k = t - 12582912.0f;
    float r = x - k * 0.693359375f;
    r = r + k * 2.12194440e-4f;
    float p = 1.9875691500e-4f;
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    p = p * (r * r) + r + 1.0f;
    union { int32_t i; float f; } scale;
    scale.i = ((int32_t)k + 127) << 23;
    return p * scale.f;
}

static inline double exp_f64(double x) { return exp(x); }

/* EWA projection of one Gaussian, in double (see torch_cpu.project_gaussians, which this mirrors):
 * everything the forward and the backward need. view: [12] world-to-camera rows (R | t); intr: fx, fy,
 * cx, cy; lim: the Jacobian's clamp of x / z and y / z (-neg_x, pos_x, -neg_y, pos_y). */
typedef struct {
    double x, y, z, zs, rx, ry, J00, J02, J11, J12, JW0[3], JW1[3], qn[4], nrm, Rq[3][3], M[3][3], F0[3], F1[3];
    double ca, cb, cc, det, A, B, C, u, v;
    int in_depth, ok, free_x, free_y;
} Ewa;

static inline void ewa(Ewa *e, const double *m, const double *q, const double *s, double o, const double *view,
                       const double *intr, const double *lim, double near, double far, double eps2d,
                       double alpha_min) {
    const double fx = intr[0], fy = intr[1], cx = intr[2], cy = intr[3];
    e->x = view[0] * m[0] + view[1] * m[1] + view[2] * m[2] + view[3];
    e->y = view[4] * m[0] + view[5] * m[1] + view[6] * m[2] + view[7];
    e->z = view[8] * m[0] + view[9] * m[1] + view[10] * m[2] + view[11];
    e->in_depth = e->z > near && e->z < far;
    e->zs = e->in_depth ? e->z : 1.0;  /* culled Gaussians get a harmless depth */
    const double zs = e->zs;
    e->u = fx * e->x / zs + cx;
    e->v = fy * e->y / zs + cy;
    double rx = e->x / zs, ry = e->y / zs;
    e->free_x = rx > lim[0] && rx < lim[1];
    e->free_y = ry > lim[2] && ry < lim[3];
    e->rx = rx < lim[0] ? lim[0] : (rx > lim[1] ? lim[1] : rx);
    e->ry = ry < lim[2] ? lim[2] : (ry > lim[3] ? lim[3] : ry);
    e->J00 = fx / zs;
    e->J02 = -fx * e->rx / zs;
    e->J11 = fy / zs;
    e->J12 = -fy * e->ry / zs;
    for (int j = 0; j < 3; ++j) {
        e->JW0[j] = e->J00 * view[j] + e->J02 * view[8 + j];
        e->JW1[j] = e->J11 * view[4 + j] + e->J12 * view[8 + j];
    }
    double nq = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    e->nrm = nq > 1e-12 ? nq : 1e-12;
    for (int k = 0; k < 4; ++k) e->qn[k] = q[k] / e->nrm;
    const double w = e->qn[0], x = e->qn[1], y = e->qn[2], z = e->qn[3];
    double R[3][3] = {{1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)},
                      {2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)},
                      {2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)}};
    for (int i = 0; i < 3; ++i)
        for (int k = 0; k < 3; ++k) {
            e->Rq[i][k] = R[i][k];
            e->M[i][k] = R[i][k] * s[k];
        }
    for (int k = 0; k < 3; ++k) {
        e->F0[k] = e->JW0[0] * e->M[0][k] + e->JW0[1] * e->M[1][k] + e->JW0[2] * e->M[2][k];
        e->F1[k] = e->JW1[0] * e->M[0][k] + e->JW1[1] * e->M[1][k] + e->JW1[2] * e->M[2][k];
    }
    e->ca = e->F0[0] * e->F0[0] + e->F0[1] * e->F0[1] + e->F0[2] * e->F0[2] + eps2d;
    e->cb = e->F0[0] * e->F1[0] + e->F0[1] * e->F1[1] + e->F0[2] * e->F1[2];
    e->cc = e->F1[0] * e->F1[0] + e->F1[1] * e->F1[1] + e->F1[2] * e->F1[2] + eps2d;
    e->det = e->ca * e->cc - e->cb * e->cb;
    e->ok = e->in_depth && e->det > 0.0 && o >= alpha_min;
    double ds = e->ok ? e->det : 1.0;
    e->A = e->cc / ds;
    e->B = -e->cb / ds;
    e->C = e->ca / ds;
}

/* contrib bit of pixel block blk of nblk (with more than 8 blocks, bit 0 stands for all of them) */
static inline uint8_t block_bit(int64_t blk, int64_t nblk) { return nblk > 8 ? (uint8_t)1 : (uint8_t)(1u << blk); }

static void *zalloc(size_t count, size_t size) {
    /* 64-byte aligned, zeroed; count rounded up so that the size is a multiple of the alignment */
    size_t bytes = (count * size + 63) / 64 * 64;
    void *p = aligned_alloc(64, bytes ? bytes : 64);
    if (p) memset(p, 0, bytes ? bytes : 64);
    return p;
}
"""

BODY = r"""
/* Kernels for one scalar type: SCALAR (float or double), EXP (exp_f32 or exp_f64) and FN(name)
 * (name_f32 or name_f64) are defined around this text.
 *
 * Conventions (those of torch_cpu.py): params is [6, N] row-major: u, v (pixel coordinates of the
 * projected mean), a, b, c (conic [[a, b], [b, c]]) and opacity; feat is [N, C] row-major; pixel (i, j)
 * has centre (j + 0.5, i + 0.5); sigma = (a dx^2 + c dy^2) / 2 + b dx dy with dx = x - u, dy = y - v;
 * alpha = min(alpha_max, opacity exp(-sigma)), skipped below alpha_min; a pixel stops before the first
 * Gaussian that would bring its transmittance below t_min.
 */

/* Forward projection of n Gaussians ([n, 3] means, [n, 4] raw quaternions (w, x, y, z), [n, 3] scales,
 * [n] opacities): [n, 2] means2d, [n, 3] conics, [n] depths (camera z), and the no-gradient culling
 * quantities of torch_cpu.Projection: visible, radii, pixel box [n, 4] and cull_q. */
void FN(project_forward)(int64_t n, const SCALAR *means, const SCALAR *quats, const SCALAR *scales,
                         const SCALAR *opac, const double *view, const double *intr, const double *lim,
                         int64_t width, int64_t height, double near, double far, double eps2d, double alpha_min,
                         SCALAR *means2d, SCALAR *conics, SCALAR *depths, uint8_t *visible, int32_t *radii,
                         int64_t *box, SCALAR *cull_q) {
    const double big = (double)(width > height ? width : height) + 1.0;
    for (int64_t g = 0; g < n; ++g) {
        double m[3] = {means[3 * g], means[3 * g + 1], means[3 * g + 2]};
        double q[4] = {quats[4 * g], quats[4 * g + 1], quats[4 * g + 2], quats[4 * g + 3]};
        double s[3] = {scales[3 * g], scales[3 * g + 1], scales[3 * g + 2]};
        double o = opac[g];
        Ewa e;
        ewa(&e, m, q, s, o, view, intr, lim, near, far, eps2d, alpha_min);
        means2d[2 * g] = (SCALAR)e.u;
        means2d[2 * g + 1] = (SCALAR)e.v;
        conics[3 * g] = (SCALAR)e.A;
        conics[3 * g + 1] = (SCALAR)e.B;
        conics[3 * g + 2] = (SCALAR)e.C;
        depths[g] = (SCALAR)e.z;
        /* alpha >= alpha_min  <=>  d^T conic d <= k, k = 2 ln(opacity / alpha_min); the ellipse's box has
         * half-widths sqrt(k cov_xx), sqrt(k cov_yy), widened by relative and absolute margins */
        double k = 2.0 * log((o > alpha_min ? o : alpha_min) / alpha_min);
        double hw = sqrt(k * (e.ca > 0 ? e.ca : 0.0)) * (1 + 1e-5) + 1e-4;
        double hh = sqrt(k * (e.cc > 0 ? e.cc : 0.0)) * (1 + 1e-5) + 1e-4;
        double j0 = ceil(e.u - hw - 0.5), j1 = floor(e.u + hw - 0.5);
        double i0 = ceil(e.v - hh - 0.5), i1 = floor(e.v + hh - 0.5);
        int fin = isfinite(j0) && isfinite(j1) && isfinite(i0) && isfinite(i1);
        int vis = e.ok && fin && j1 >= 0 && j0 <= (double)(width - 1) && i1 >= 0 && i0 <= (double)(height - 1)
                  && j0 <= j1 && i0 <= i1;
        visible[g] = (uint8_t)vis;
        int64_t *b = box + 4 * g;
        if (vis) {
            b[0] = (int64_t)clamp_d(j0, 0, (double)(width - 1));
            b[1] = (int64_t)clamp_d(j1, 0, (double)(width - 1));
            b[2] = (int64_t)clamp_d(i0, 0, (double)(height - 1));
            b[3] = (int64_t)clamp_d(i1, 0, (double)(height - 1));
            double r = ceil(hw > hh ? hw : hh);
            radii[g] = (int32_t)(r < big ? r : big);
        } else {
            b[0] = b[1] = b[2] = b[3] = 0;
            radii[g] = 0;
        }
        cull_q[g] = (SCALAR)(k * (1 + 1e-4) + 1e-6);
    }
}

/* Backward of project_forward: from the gradients of means2d [n, 2], conics [n, 3] and depths [n] (each
 * may be NULL), WRITES those of means [n, 3], raw quaternions [n, 4] and scales [n, 3]. Gaussians with
 * no incoming gradient are skipped (their outputs are zero). */
void FN(project_backward)(int64_t n, const SCALAR *means, const SCALAR *quats, const SCALAR *scales,
                          const SCALAR *opac, const double *view, const double *intr, const double *lim,
                          double near, double far, double eps2d, double alpha_min, const SCALAR *g_means2d,
                          const SCALAR *g_conics, const SCALAR *g_depths, SCALAR *g_means, SCALAR *g_quats,
                          SCALAR *g_scales) {
    const double fx = intr[0], fy = intr[1];
    for (int64_t g = 0; g < n; ++g) {
        double gu = g_means2d ? g_means2d[2 * g] : 0.0, gv = g_means2d ? g_means2d[2 * g + 1] : 0.0;
        double gA = g_conics ? g_conics[3 * g] : 0.0, gB = g_conics ? g_conics[3 * g + 1] : 0.0;
        double gC = g_conics ? g_conics[3 * g + 2] : 0.0, gz = g_depths ? g_depths[g] : 0.0;
        for (int k = 0; k < 3; ++k) g_means[3 * g + k] = g_scales[3 * g + k] = (SCALAR)0;
        for (int k = 0; k < 4; ++k) g_quats[4 * g + k] = (SCALAR)0;
        if (gu == 0.0 && gv == 0.0 && gA == 0.0 && gB == 0.0 && gC == 0.0 && gz == 0.0) continue;
        double m[3] = {means[3 * g], means[3 * g + 1], means[3 * g + 2]};
        double q[4] = {quats[4 * g], quats[4 * g + 1], quats[4 * g + 2], quats[4 * g + 3]};
        double s[3] = {scales[3 * g], scales[3 * g + 1], scales[3 * g + 2]};
        Ewa e;
        ewa(&e, m, q, s, opac[g], view, intr, lim, near, far, eps2d, alpha_min);
        /* conic (A, B, C) = (cc, -cb, ca) / det, det = ca cc - cb^2 (det taken as 1 where culled) */
        double gca, gcb, gcc;
        if (e.ok) {
            const double A = e.A, B = e.B, C = e.C;
            gca = -(gA * A * A + gB * A * B + gC * B * B);
            gcb = -(2.0 * gA * A * B + gB * (A * C + B * B) + 2.0 * gC * B * C);
            gcc = -(gA * B * B + gB * B * C + gC * C * C);
        } else {
            gca = gC;
            gcb = -gB;
            gcc = gA;
        }
        /* cov = F F^T + eps2d I with F = [F0; F1] = JW M */
        double dF0[3], dF1[3], dJW0[3], dJW1[3], dM[3][3];
        for (int k = 0; k < 3; ++k) {
            dF0[k] = 2.0 * gca * e.F0[k] + gcb * e.F1[k];
            dF1[k] = gcb * e.F0[k] + 2.0 * gcc * e.F1[k];
        }
        for (int i = 0; i < 3; ++i) {
            dJW0[i] = dF0[0] * e.M[i][0] + dF0[1] * e.M[i][1] + dF0[2] * e.M[i][2];
            dJW1[i] = dF1[0] * e.M[i][0] + dF1[1] * e.M[i][1] + dF1[2] * e.M[i][2];
            for (int k = 0; k < 3; ++k) dM[i][k] = e.JW0[i] * dF0[k] + e.JW1[i] * dF1[k];
        }
        /* M = Rq diag(s) */
        double G[3][3];
        for (int k = 0; k < 3; ++k) {
            g_scales[3 * g + k] = (SCALAR)(dM[0][k] * e.Rq[0][k] + dM[1][k] * e.Rq[1][k] + dM[2][k] * e.Rq[2][k]);
            for (int i = 0; i < 3; ++i) G[i][k] = dM[i][k] * s[k];
        }
        /* Rq of the normalised quaternion (w, x, y, z) */
        const double w = e.qn[0], x = e.qn[1], y = e.qn[2], z = e.qn[3];
        double dq[4];
        dq[0] = 2.0 * (-z * G[0][1] + y * G[0][2] + z * G[1][0] - x * G[1][2] - y * G[2][0] + x * G[2][1]);
        dq[1] = 2.0 * (y * G[0][1] + z * G[0][2] + y * G[1][0] - 2.0 * x * G[1][1] - w * G[1][2] + z * G[2][0]
                       + w * G[2][1] - 2.0 * x * G[2][2]);
        dq[2] = 2.0 * (-2.0 * y * G[0][0] + x * G[0][1] + w * G[0][2] + x * G[1][0] + z * G[1][2] - w * G[2][0]
                       + z * G[2][1] - 2.0 * y * G[2][2]);
        dq[3] = 2.0 * (-2.0 * z * G[0][0] - w * G[0][1] + x * G[0][2] + w * G[1][0] - 2.0 * z * G[1][1]
                       + y * G[1][2] + x * G[2][0] + y * G[2][1]);
        double dot = w * dq[0] + x * dq[1] + y * dq[2] + z * dq[3];
        int normalised = e.nrm > 1e-12;  /* below, the norm is clamped: no gradient through it */
        for (int k = 0; k < 4; ++k)
            g_quats[4 * g + k] = (SCALAR)((dq[k] - (normalised ? e.qn[k] * dot : 0.0)) / e.nrm);
        /* JW = J R_view; J = [[fx / zs, 0, -fx rx / zs], [0, fy / zs, -fy ry / zs]], rx = clamp(x / zs) */
        double dJ00 = 0, dJ02 = 0, dJ11 = 0, dJ12 = 0;
        for (int j = 0; j < 3; ++j) {
            dJ00 += dJW0[j] * view[j];
            dJ02 += dJW0[j] * view[8 + j];
            dJ11 += dJW1[j] * view[4 + j];
            dJ12 += dJW1[j] * view[8 + j];
        }
        const double zs = e.zs;
        double gx = gu * fx / zs, gy = gv * fy / zs;
        double gzs = -gu * fx * e.x / (zs * zs) - gv * fy * e.y / (zs * zs);
        gzs += -dJ00 * fx / (zs * zs) - dJ11 * fy / (zs * zs);
        gzs += dJ02 * fx * e.rx / (zs * zs) + dJ12 * fy * e.ry / (zs * zs);
        double grx = -dJ02 * fx / zs, gry = -dJ12 * fy / zs;
        if (e.free_x) {
            gx += grx / zs;
            gzs -= grx * e.x / (zs * zs);
        }
        if (e.free_y) {
            gy += gry / zs;
            gzs -= gry * e.y / (zs * zs);
        }
        double gzz = gz + (e.in_depth ? gzs : 0.0);
        for (int k = 0; k < 3; ++k)
            g_means[3 * g + k] = (SCALAR)(view[k] * gx + view[4 + k] * gy + view[8 + k] * gzz);
    }
}

/* Upper bound of the layout's rows: the tiles of the visible Gaussians' pixel boxes. */
int64_t FN(layout_bound)(int64_t n_vis, const int64_t *order, const int64_t *box, int64_t ts) {
    int64_t total = 0;
    for (int64_t r = 0; r < n_vis; ++r) {
        const int64_t *bx = box + 4 * order[r];
        total += (bx[1] / ts - bx[0] / ts + 1) * (bx[3] / ts - bx[2] / ts + 1);
    }
    return total;
}

/* The tile layout: for the visible Gaussians `order` (front to back), one row per tile of their pixel box
 * whose pixel-centre rectangle meets the ellipse q(d) = a dx^2 + 2 b dx dy + c dy^2 <= qmax, ordered by
 * (tile, depth): tile t's Gaussians are rows[tile_start[t] .. tile_start[t + 1]). Exact per band of tiles:
 * over dy in the band's pixel-centre rows the ellipse's chord spans dx = (-b dy -+ sqrt(a qmax - D dy^2)) / a
 * (D = ac - b^2); its right end is concave in dy and peaks at the rightmost point dy* = -b sqrt(qmax / (c D)),
 * so the band's largest dx is at dy* clamped into the band, the smallest at -dy* clamped; a tile meets the
 * ellipse iff its dx range overlaps the band's. params is [n, 6] (u, v, a, b, c, opacity); rows has room
 * for cap (>= layout_bound) entries. Returns the number of rows, -1 when out of memory. */
int64_t FN(layout_build)(int64_t n_vis, const int64_t *order, const SCALAR *params, const SCALAR *qmax,
                         const int64_t *box, int64_t ts, int64_t tiles_x, int64_t tiles_y, int64_t width,
                         int64_t height, int64_t *tile_start, int32_t *rows, int64_t cap) {
    const int64_t n_tiles = tiles_x * tiles_y;
    int32_t *tile_of = (int32_t *)malloc(sizeof(int32_t) * (size_t)(cap > 0 ? cap : 1));
    int32_t *kept = (int32_t *)malloc(sizeof(int32_t) * (size_t)(n_vis > 0 ? n_vis : 1));
    int64_t *cursor = (int64_t *)calloc((size_t)n_tiles + 1, sizeof(int64_t));
    if (!tile_of || !kept || !cursor) {
        free(tile_of); free(kept); free(cursor);
        return -1;
    }
    int64_t total = 0;
    for (int64_t t = 0; t <= n_tiles; ++t) tile_start[t] = 0;
    for (int64_t r = 0; r < n_vis; ++r) {
        const int64_t g = order[r];
        const SCALAR *pg = params + 6 * g;
        const double u = pg[0], v = pg[1], a = pg[2] > 1e-30 ? pg[2] : 1e-30, b = pg[3];
        const double c = pg[4] > 1e-30 ? pg[4] : 1e-30, q = qmax[g];
        const double det = a * c - b * b > 1e-30 ? a * c - b * b : 1e-30;
        const double reach = sqrt(q * a / det), dy_star = -b * sqrt(q / (c * det)), aq = a * q;
        const int64_t *bx = box + 4 * g;
        const int64_t tx0 = bx[0] / ts, tx1 = bx[1] / ts, ty0 = bx[2] / ts, ty1 = bx[3] / ts;
        const int single = tx0 == tx1 && ty0 == ty1;
        int32_t k = 0;
        for (int64_t ty = ty0; ty <= ty1; ++ty) {
            int64_t first = tx0, end = tx1;  /* the band's tiles that meet the ellipse */
            if (!single) {
                const double y0 = (double)(ty * ts) + 0.5 - v;
                const double y1 = (double)(min_i64((ty + 1) * ts, height) - 1) + 0.5 - v;
                const double lo = y0 > -reach ? y0 : -reach, hi = y1 < reach ? y1 : reach;
                if (lo > hi) continue;  /* the band misses the ellipse */
                const double yr = clamp_d(dy_star, lo, hi), yl = clamp_d(-dy_star, lo, hi);
                const double rr = aq - det * yr * yr, rl = aq - det * yl * yl;
                const double x_max = (sqrt(rr > 0 ? rr : 0) - b * yr) / a;
                const double x_min = (-sqrt(rl > 0 ? rl : 0) - b * yl) / a;
                /* tile tx spans pixel centres dx in [tx ts + 0.5 - u, tx ts + ts - 0.5 - u] */
                while (first <= end && (double)(first * ts + ts) - 0.5 - u < x_min) ++first;
                while (end >= first && (double)(end * ts) + 0.5 - u > x_max) --end;
            }
            for (int64_t tx = first; tx <= end; ++tx) {
                const int32_t t = (int32_t)(ty * tiles_x + tx);
                tile_of[total++] = t;
                tile_start[t + 1] += 1;
                ++k;
            }
        }
        kept[r] = k;
    }
    for (int64_t t = 0; t < n_tiles; ++t) tile_start[t + 1] += tile_start[t];
    for (int64_t r = 0, e = 0; r < n_vis; ++r) {
        const int32_t g = (int32_t)order[r];
        for (int32_t k = 0; k < kept[r]; ++k, ++e) {
            const int32_t t = tile_of[e];
            rows[tile_start[t] + cursor[t]++] = g;
        }
    }
    free(tile_of); free(kept); free(cursor);
    return total;
}

/* Sum of LANES floats as a fixed tree (the same order at any vector width). */
static inline double FN(lane_sum)(const SCALAR *x) {
    return (double)(((x[0] + x[1]) + (x[2] + x[3])) + ((x[4] + x[5]) + (x[6] + x[7])));
}

/* The tile's pixels are processed in blocks of LANES lanes; a block is skipped for a Gaussian when none of
 * its pixels is still compositing with sigma below the Gaussian's bound smax (alpha < alpha_min there for
 * sure): an exact shortcut, as the skipped pairs change nothing. Blocks of a row that composite are flagged
 * in contrib (block_bit). */

/* One block of one Gaussian in the forward: returns whether any lane composited. The arrays are the block's
 * LANES lanes; nothing changes when no lane is still compositing with sigma <= smax. */
NOINLINE static int32_t FN(fw_block)(const SCALAR *restrict px, const SCALAR *restrict py, SCALAR *restrict T,
                                     int32_t *restrict act, int32_t *restrict lj, int32_t *restrict cnt,
                                     SCALAR *restrict w, SCALAR *restrict sig, SCALAR u, SCALAR v, SCALAR a,
                                     SCALAR b, SCALAR c, SCALAR o, SCALAR smax, SCALAR amin, SCALAR amax,
                                     SCALAR tmin, int32_t next) {
    int32_t live = 0;
    for (int64_t p = 0; p < LANES; ++p) {
        SCALAR dx = px[p] - u, dy = py[p] - v;
        sig[p] = (SCALAR)0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy;
        live |= act[p] & (sig[p] <= smax);
    }
    if (!live) return 0;
    int32_t any_ok = 0;
    for (int64_t p = 0; p < LANES; ++p) {
        SCALAR al = o * EXP(-sig[p]);
        al = al < amax ? al : amax;
        SCALAR tp = T[p], tn = tp * ((SCALAR)1 - al);
        /* int32 masks combined with & and ^: the form the vectoriser if-converts */
        int32_t ok = act[p] & (al >= amin);
        int32_t stop = ok & (tn < tmin);
        ok = ok ^ stop;
        act[p] = act[p] ^ stop;
        w[p] = ok ? al * tp : (SCALAR)0;
        T[p] = ok ? tn : tp;
        lj[p] = ok ? next : lj[p];
        cnt[p] += ok;
        any_ok |= ok;
    }
    return any_ok;
}

/* Forward compositing, tile by tile: for each Gaussian of the tile's list (front to back) all of the
 * tile's pixels at once (vector lanes, block by block), until every pixel has stopped. params is [N, 6]
 * (u, v, a, b, c, opacity), smax [N] the sigma beyond which alpha < alpha_min, feat [N, C]. Writes
 * out[H * W, C], t_end[H * W] (final transmittance) and last[H * W] (one past the list position of the
 * pixel's last composited Gaussian, 0 for none), and contrib[rows] (zeroed by the caller; see above);
 * returns the number of composited pairs, -1 when out of memory. With trip_pix non-NULL, also lists every
 * composited pair: flat pixel index, Gaussian and weight alpha T (trip_cap long: the number of pairs,
 * known from an earlier call). */
HOT int64_t FN(forward)(const SCALAR *params, const SCALAR *smax, const SCALAR *feat, int64_t C,
                        const int64_t *tile_start, const int32_t *rows, int64_t ts, int64_t tiles_x, int64_t tiles_y,
                        int64_t width, int64_t height, double alpha_min, double alpha_max, double t_min, SCALAR *out,
                        SCALAR *t_end, int32_t *last, uint8_t *contrib, int64_t *trip_pix, int32_t *trip_g,
                        SCALAR *trip_w, int64_t trip_cap) {
    const int64_t P = ts * ts, PP = (P + LANES - 1) / LANES * LANES, nblk = PP / LANES;
    const SCALAR amin = (SCALAR)alpha_min, amax = (SCALAR)alpha_max, tmin = (SCALAR)t_min;
    int64_t n_trip = 0;
    SCALAR *px = (SCALAR *)zalloc((size_t)PP * (4 + (size_t)C) + LANES, sizeof(SCALAR));
    int32_t *lj = (int32_t *)zalloc((size_t)PP * 3, sizeof(int32_t));
    if (!px || !lj) {
        free(px); free(lj);
        return -1;
    }
    SCALAR *py = px + PP, *T = py + PP, *w = T + PP, *acc = w + PP, *sig = acc + C * PP;
    int32_t *act = lj + PP, *cnt = act + PP;  /* act: the pixel is still compositing */
    for (int64_t ty = 0; ty < tiles_y; ++ty) {
        for (int64_t tx = 0; tx < tiles_x; ++tx) {
            const int64_t t = ty * tiles_x + tx, s0 = tile_start[t], m = tile_start[t + 1] - s0;
            for (int64_t p = 0; p < PP; ++p) {
                int64_t ix = tx * ts + p % ts, iy = ty * ts + p / ts;
                px[p] = (SCALAR)ix + (SCALAR)0.5;
                py[p] = (SCALAR)iy + (SCALAR)0.5;
                act[p] = p < P && ix < width && iy < height;
                T[p] = (SCALAR)1;
                lj[p] = 0;
            }
            memset(acc, 0, sizeof(SCALAR) * (size_t)(C * PP));
            for (int64_t j = 0; j < m; ++j) {
                const int64_t g = rows[s0 + j];
                if (j + 2 < m) {  /* rows are in depth order, Gaussians anywhere in memory: fetch ahead */
                    const int64_t g2 = rows[s0 + j + 2];
                    PREFETCH(params + 6 * g2);
                    PREFETCH(feat + C * g2);
                    PREFETCH(smax + g2);
                }
                const SCALAR *pg = params + 6 * g;
                const SCALAR u = pg[0], v = pg[1], a = pg[2], b = pg[3], c = pg[4], o = pg[5], sm = smax[g];
                const int32_t next = (int32_t)(j + 1);
                uint8_t bits = 0;
                const SCALAR *f = feat + C * g;
                for (int64_t blk = 0; blk < nblk; ++blk) {
                    const int64_t b0 = blk * LANES;
                    if (!FN(fw_block)(px + b0, py + b0, T + b0, act + b0, lj + b0, cnt + b0, w + b0, sig, u, v, a,
                                      b, c, o, sm, amin, amax, tmin, next))
                        continue;  /* nothing reachable, or stops only (T unchanged, nothing added) */
                    bits |= block_bit(blk, nblk);
                    for (int64_t k = 0; k < C; ++k) {
                        const SCALAR fk = f[k];
                        SCALAR *restrict ak = acc + k * PP + b0;
                        const SCALAR *restrict wb = w + b0;
                        for (int64_t p = 0; p < LANES; ++p) ak[p] += wb[p] * fk;
                    }
                    if (trip_pix) {
                        for (int64_t p = b0; p < b0 + LANES; ++p) {
                            if (w[p] > (SCALAR)0 && n_trip < trip_cap) {
                                trip_pix[n_trip] = (ty * ts + p / ts) * width + tx * ts + p % ts;
                                trip_g[n_trip] = (int32_t)g;
                                trip_w[n_trip] = w[p];
                                ++n_trip;
                            }
                        }
                    }
                }
                contrib[s0 + j] = bits;
                if ((j & 7) == 7) {  /* every pixel stopped: the rest of the list is hidden */
                    int32_t any = 0;
                    for (int64_t p = 0; p < PP; ++p) any |= act[p];
                    if (!any) break;
                }
            }
            for (int64_t p = 0; p < P; ++p) {
                int64_t ix = tx * ts + p % ts, iy = ty * ts + p / ts;
                if (ix >= width || iy >= height) continue;
                int64_t q = iy * width + ix;
                for (int64_t k = 0; k < C; ++k) out[C * q + k] = acc[k * PP + p];
                t_end[q] = T[p];
                last[q] = lj[p];
            }
        }
    }
    int64_t pairs = 0;
    for (int64_t p = 0; p < PP; ++p) pairs += cnt[p];
    free(px); free(lj);
    return pairs;
}

/* One block of one list position in the backward, first part: for every lane (pixel), the pair's geometry,
 * alpha, 1 / (1 - alpha), the transmittance before it (recovered from the one after), its weight and
 * masks. Separate functions with restrict parameters, so that the compiler vectorises their loops without
 * runtime overlap checks; not inlined: GCC 12 miscompiled them inlined into the list loop (wrong
 * gradients at -O3 only). */
NOINLINE static void FN(bw_alpha)(const SCALAR *restrict px, const SCALAR *restrict py, const SCALAR *restrict T,
                                  const int32_t *restrict lj, int32_t j32, SCALAR u, SCALAR v, SCALAR a, SCALAR b,
                                  SCALAR c, SCALAR o, SCALAR amin, SCALAR amax, SCALAR *restrict dxs,
                                  SCALAR *restrict dys, SCALAR *restrict als, SCALAR *restrict oks,
                                  SCALAR *restrict frees, SCALAR *restrict oms, SCALAR *restrict tbs,
                                  SCALAR *restrict ws) {
    for (int64_t p = 0; p < LANES; ++p) {
        SCALAR dx = px[p] - u, dy = py[p] - v;
        SCALAR sig = (SCALAR)0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy;
        SCALAR raw = o * EXP(-sig);
        SCALAR al = raw < amax ? raw : amax;
        int32_t ok = (j32 < lj[p]) & (al >= amin);
        SCALAR inv = (SCALAR)1 / ((SCALAR)1 - al), tb = T[p] * inv;  /* one division per lane */
        dxs[p] = dx;
        dys[p] = dy;
        als[p] = al;
        oks[p] = ok ? (SCALAR)1 : (SCALAR)0;
        frees[p] = (ok & (raw <= amax)) ? (SCALAR)1 : (SCALAR)0;  /* composited, alpha not clamped */
        oms[p] = inv;
        tbs[p] = tb;
        ws[p] = ok ? al * tb : (SCALAR)0;
    }
}

/* Second part, channel by channel with the block's lanes as vector lanes: qs_p = sum_k g_p,k f_k (for the
 * parameters' gradients; qs NULL: not wanted) and (accp non-NULL) the lanes' partial sums accp[k][l] +=
 * w_l g_l,k of the Gaussian's channel gradients. G [C, PP] points at the block's first lane. */
NOINLINE static void FN(bw_channels)(int64_t PP, int64_t C, const SCALAR *restrict G, const SCALAR *restrict f,
                                     const SCALAR *restrict ws, SCALAR *restrict qs, SCALAR *restrict accp) {
    if (qs) {
        for (int64_t p = 0; p < LANES; ++p) qs[p] = (SCALAR)0;
        for (int64_t k = 0; k < C; ++k) {
            const SCALAR fk = f[k];
            const SCALAR *restrict gk = G + k * PP;
            for (int64_t p = 0; p < LANES; ++p) qs[p] += gk[p] * fk;
        }
    }
    if (accp) {
        for (int64_t k = 0; k < C; ++k) {
            const SCALAR *restrict gk = G + k * PP;
            SCALAR *restrict ak = accp + k * LANES;
            for (int64_t p = 0; p < LANES; ++p) ak[p] += ws[p] * gk[p];
        }
    }
}

/* Third part: d loss / d alpha per lane, the running sums R and transmittances T moved past the pair,
 * and the lanes' partial sums of the gradients of (u, v, a, b, c) and of opacity x opacity (added). */
NOINLINE static void FN(bw_params)(const SCALAR *restrict tbs, const SCALAR *restrict qs, const SCALAR *restrict ga,
                                   const SCALAR *restrict oms, const SCALAR *restrict ws, const SCALAR *restrict oks,
                                   const SCALAR *restrict frees, const SCALAR *restrict als,
                                   const SCALAR *restrict dxs, const SCALAR *restrict dys, SCALAR a, SCALAR b,
                                   SCALAR c, SCALAR *restrict R, SCALAR *restrict T, SCALAR *restrict pu,
                                   SCALAR *restrict pv, SCALAR *restrict pa, SCALAR *restrict pb,
                                   SCALAR *restrict pc, SCALAR *restrict po) {
    for (int64_t p = 0; p < LANES; ++p) {
        /* out = sum_i w_i f_i: d out / d alpha_i = T_i f_i - (sum_{j>i} w_j f_j) / (1 - alpha_i) */
        SCALAR g_alpha = tbs[p] * qs[p] - (R[p] - ga[p]) * oms[p];  /* oms: 1 / (1 - alpha) */
        R[p] += ws[p] * qs[p];
        T[p] = oks[p] > (SCALAR)0 ? tbs[p] : T[p];
        SCALAR gal = frees[p] * als[p] * g_alpha;  /* d alpha / d sigma = -alpha */
        SCALAR dx = dxs[p], dy = dys[p];
        pu[p] += gal * (a * dx + b * dy);  /* d sigma / d u = -(a dx + b dy) */
        pv[p] += gal * (b * dx + c * dy);
        pa[p] -= gal * (SCALAR)0.5 * dx * dx;
        pb[p] -= gal * dx * dy;
        pc[p] -= gal * (SCALAR)0.5 * dy * dy;
        po[p] += gal;  /* d alpha / d opacity = alpha / opacity */
    }
}

/* Third part when the Gaussians' parameters want no gradient: only the transmittances move past the pair. */
NOINLINE static void FN(bw_advance)(const SCALAR *restrict tbs, const SCALAR *restrict oks, SCALAR *restrict T) {
    for (int64_t p = 0; p < LANES; ++p) T[p] = oks[p] > (SCALAR)0 ? tbs[p] : T[p];
}

/* Backward of forward(): with g_out[H * W, C] (may be NULL) the gradient of the composited channels and
 * g_acc[H * W] (may be NULL) that of the accumulated alpha 1 - t_end, ADDS the gradients of params into
 * grad_params[N, 6] and of feat into grad_feat[N, C] (double; either may be NULL: not wanted). Walks each
 * tile's list back to front with all its pixels at once, block by block where the forward composited,
 * recovering each pixel's transmittance by division (1 - alpha >= 1 - alpha_max). Pairs whose alpha was
 * clamped at alpha_max pass no gradient to the mean, conic or opacity. Returns 0, or -1 when out of memory. */
HOT int FN(backward)(const SCALAR *params, const SCALAR *feat, int64_t C, const int64_t *tile_start,
                     const int32_t *rows, int64_t ts, int64_t tiles_x, int64_t tiles_y, int64_t width, int64_t height,
                     double alpha_min, double alpha_max, const SCALAR *t_end, const int32_t *last,
                     const uint8_t *contrib, const SCALAR *g_out, const SCALAR *g_acc, double *grad_params,
                     double *grad_feat) {
    const int64_t P = ts * ts, PP = (P + LANES - 1) / LANES * LANES, nblk = PP / LANES;
    const SCALAR amin = (SCALAR)alpha_min, amax = (SCALAR)alpha_max;
    SCALAR *px = (SCALAR *)zalloc((size_t)PP * (5 + (size_t)C) + 15 * LANES + (size_t)C * LANES, sizeof(SCALAR));
    int32_t *lj = (int32_t *)zalloc((size_t)PP, sizeof(int32_t));
    if (!px || !lj) {
        free(px); free(lj);
        return -1;
    }
    SCALAR *py = px + PP, *T = py + PP, *R = T + PP, *ga = R + PP, *G = ga + PP;
    SCALAR *dxs = G + C * PP, *dys = dxs + LANES, *als = dys + LANES, *oks = als + LANES, *frees = oks + LANES;
    SCALAR *oms = frees + LANES, *tbs = oms + LANES, *ws = tbs + LANES, *qs = ws + LANES, *part = qs + LANES;
    SCALAR *accp = part + 6 * LANES;  /* [C, LANES] partial sums of the channel gradients */
    for (int64_t ty = 0; ty < tiles_y; ++ty) {
        for (int64_t tx = 0; tx < tiles_x; ++tx) {
            const int64_t t = ty * tiles_x + tx, s0 = tile_start[t];
            int32_t jmax = 0;
            for (int64_t p = 0; p < PP; ++p) {
                int64_t ix = tx * ts + p % ts, iy = ty * ts + p / ts, q = iy * width + ix;
                int inside = p < P && ix < width && iy < height;
                px[p] = (SCALAR)ix + (SCALAR)0.5;
                py[p] = (SCALAR)iy + (SCALAR)0.5;
                lj[p] = inside ? last[q] : 0;
                T[p] = inside ? t_end[q] : (SCALAR)1;
                R[p] = (SCALAR)0;
                /* accumulated alpha 1 - T_end: d / d alpha_i = T_end / (1 - alpha_i) */
                ga[p] = (inside && g_acc) ? g_acc[q] * t_end[q] : (SCALAR)0;
                for (int64_t k = 0; k < C; ++k) G[k * PP + p] = (inside && g_out) ? g_out[C * q + k] : (SCALAR)0;
                jmax = lj[p] > jmax ? lj[p] : jmax;
            }
            for (int64_t j = (int64_t)jmax - 1; j >= 0; --j) {
                const uint8_t bits = contrib[s0 + j];
                if (j >= 2) {  /* fetch ahead the rows' Gaussians and their gradients (anywhere in memory) */
                    const int64_t g2 = rows[s0 + j - 2];
                    PREFETCH(params + 6 * g2);
                    PREFETCH(feat + C * g2);
                    if (grad_params) PREFETCH(grad_params + 6 * g2);
                    if (grad_feat) PREFETCH(grad_feat + C * g2);
                }
                if (!bits) continue;  /* composited nowhere: no gradient, T unchanged */
                const int64_t g = rows[s0 + j];
                const SCALAR *pg = params + 6 * g;
                const SCALAR u = pg[0], v = pg[1], a = pg[2], b = pg[3], c = pg[4], o = pg[5];
                const SCALAR *f = feat + C * g;
                for (int64_t l = 0; l < 6 * LANES; ++l) part[l] = (SCALAR)0;
                if (grad_feat)
                    for (int64_t l = 0; l < C * LANES; ++l) accp[l] = (SCALAR)0;
                for (int64_t blk = 0; blk < nblk; ++blk) {
                    if (nblk <= 8 && !(bits & (1u << blk))) continue;
                    const int64_t b0 = blk * LANES;
                    FN(bw_alpha)(px + b0, py + b0, T + b0, lj + b0, (int32_t)j, u, v, a, b, c, o, amin, amax, dxs,
                                 dys, als, oks, frees, oms, tbs, ws);
                    FN(bw_channels)(PP, C, G + b0, f, ws, grad_params ? qs : NULL, grad_feat ? accp : NULL);
                    if (!grad_params) {
                        FN(bw_advance)(tbs, oks, T + b0);
                    } else {
                        FN(bw_params)(tbs, qs, ga + b0, oms, ws, oks, frees, als, dxs, dys, a, b, c, R + b0, T + b0,
                                      part, part + LANES, part + 2 * LANES, part + 3 * LANES, part + 4 * LANES,
                                      part + 5 * LANES);
                    }
                }
                if (grad_feat) {
                    double *gf = grad_feat + C * g;
                    for (int64_t k = 0; k < C; ++k) gf[k] += FN(lane_sum)(accp + k * LANES);
                }
                if (grad_params) {
                    double *gp = grad_params + 6 * g;
                    for (int k = 0; k < 5; ++k) gp[k] += FN(lane_sum)(part + k * LANES);
                    gp[5] += FN(lane_sum)(part + 5 * LANES) / (double)o;
                }
            }
        }
    }
    free(px); free(lj);
    return 0;
}
/* ---- HexPlane (methods/gaussians/hexplane.py) ----------------------------------------------------
 * planes holds, per level l: the three spatial planes [3, R_l, R_l, C] then the three time planes
 * [3, T, R_l, C], channels last, at offsets[2 l] and offsets[2 l + 1]; res[l] = R_l. A point's plane
 * coordinates (x, y) in [-1, 1] (spatial planes xy, xz, yz; time planes (x, t), (y, t), (z, t)) are sampled
 * as grid_sample does with align_corners=True, padding_mode="border", bilinear: i = (x + 1) / 2 (size - 1)
 * clipped to [0, size - 1] (no gradient where clipped), corners past the last row or column count as 0.
 * The feature of level l is the product over the six planes, channel by channel. */

typedef struct { int64_t i0, j0; SCALAR fx, fy, gx, gy; int in_x, in_y; } FN(Corner);

static inline void FN(locate)(FN(Corner) *k, SCALAR x, SCALAR y, int64_t w, int64_t h) {
    SCALAR ix = (x + (SCALAR)1) / (SCALAR)2 * (SCALAR)(w - 1), iy = (y + (SCALAR)1) / (SCALAR)2 * (SCALAR)(h - 1);
    /* d i / d x of the clipped coordinate: (size - 1) / 2 inside, 0 where clipped (as torch) */
    k->gx = (ix <= (SCALAR)0 || ix >= (SCALAR)(w - 1)) ? (SCALAR)0 : (SCALAR)(w - 1) / (SCALAR)2;
    k->gy = (iy <= (SCALAR)0 || iy >= (SCALAR)(h - 1)) ? (SCALAR)0 : (SCALAR)(h - 1) / (SCALAR)2;
    ix = ix < (SCALAR)0 ? (SCALAR)0 : (ix > (SCALAR)(w - 1) ? (SCALAR)(w - 1) : ix);
    iy = iy < (SCALAR)0 ? (SCALAR)0 : (iy > (SCALAR)(h - 1) ? (SCALAR)(h - 1) : iy);
    SCALAR fx0 = floor(ix), fy0 = floor(iy);
    k->j0 = (int64_t)fx0;
    k->i0 = (int64_t)fy0;
    k->fx = ix - fx0;
    k->fy = iy - fy0;
    k->in_x = k->j0 + 1 < w;  /* the next column exists */
    k->in_y = k->i0 + 1 < h;
}

/* v[c] = the bilinear sample of plane [h, w, C] at k. */
static inline void FN(sample)(const SCALAR *plane, int64_t w, int64_t C, const FN(Corner) *k, SCALAR *v) {
    const SCALAR wnw = ((SCALAR)1 - k->fx) * ((SCALAR)1 - k->fy), wne = k->fx * ((SCALAR)1 - k->fy);
    const SCALAR wsw = ((SCALAR)1 - k->fx) * k->fy, wse = k->fx * k->fy;
    const SCALAR *nw = plane + (k->i0 * w + k->j0) * C;
#pragma GCC ivdep
    for (int64_t c = 0; c < C; ++c) v[c] = wnw * nw[c];
    if (k->in_x) {
#pragma GCC ivdep
        for (int64_t c = 0; c < C; ++c) v[c] += wne * nw[C + c];
    }
    if (k->in_y) {
        const SCALAR *sw = nw + w * C;
#pragma GCC ivdep
        for (int64_t c = 0; c < C; ++c) v[c] += wsw * sw[c];
        if (k->in_x) {
#pragma GCC ivdep
            for (int64_t c = 0; c < C; ++c) v[c] += wse * sw[C + c];
        }
    }
}

/* Sum of x[0 .. C) in a fixed order (LANES partial sums, then a tree). */
static inline SCALAR FN(chan_sum)(const SCALAR *x, int64_t C) {
    SCALAR part[LANES] = {0};
    int64_t c0 = 0;
    for (; c0 + LANES <= C; c0 += LANES)
        for (int l = 0; l < LANES; ++l) part[l] += x[c0 + l];
    for (int l = 0; c0 + l < C; ++l) part[l] += x[c0 + l];
    return ((part[0] + part[1]) + (part[2] + part[3])) + ((part[4] + part[5]) + (part[6] + part[7]));
}

/* One corner of one plane in the backward: the plane's gradient there, and per channel the corner's part
 * of d loss / d fx and d loss / d fy (ax, ay: d weight / d fx, d fy). */
static inline void FN(corner_bw)(int64_t C, const SCALAR *P, SCALAR *G, const SCALAR *gv, SCALAR wgt, SCALAR ax,
                                 SCALAR ay, SCALAR *dx, SCALAR *dy) {
#pragma GCC ivdep
    for (int64_t c = 0; c < C; ++c) {
        SCALAR pg = P[c] * gv[c];
        G[c] += wgt * gv[c];
        dx[c] += ax * pg;
        dy[c] += ay * pg;
    }
}

/* The six planes of level l: pointers, widths and heights, and the point's corners on them. */
static inline void FN(hex_level)(const SCALAR *planes, const int64_t *offsets, const int64_t *res, int64_t T,
                                 int64_t C, int64_t l, const SCALAR *q, SCALAR t, const SCALAR **pl, int64_t *pw,
                                 FN(Corner) *k) {
    const int64_t r = res[l];
    static const int pairs[3][2] = {{0, 1}, {0, 2}, {1, 2}};
    for (int m = 0; m < 3; ++m) {
        pl[m] = planes + offsets[2 * l] + (int64_t)m * r * r * C;
        pw[m] = r;
        FN(locate)(&k[m], q[pairs[m][0]], q[pairs[m][1]], r, r);
        pl[3 + m] = planes + offsets[2 * l + 1] + (int64_t)m * T * r * C;
        pw[3 + m] = r;
        FN(locate)(&k[3 + m], q[m], t, r, T);
    }
}

/* feat[n, L * C]: level l's features in columns l C .. (l + 1) C. buf: 6 C scratch. */
HOT void FN(hex_forward)(int64_t n, const SCALAR *p, const SCALAR *tt, int64_t L, const SCALAR *planes,
                     const int64_t *offsets, const int64_t *res, int64_t T, int64_t C, SCALAR *feat) {
    SCALAR *v = (SCALAR *)malloc(sizeof(SCALAR) * 6 * (size_t)C);
    if (!v) return;
    for (int64_t i = 0; i < n; ++i) {
        for (int64_t l = 0; l < L; ++l) {
            const SCALAR *pl[6];
            int64_t pw[6];
            FN(Corner) k[6];
            FN(hex_level)(planes, offsets, res, T, C, l, p + 3 * i, tt[i], pl, pw, k);
            for (int m = 0; m < 6; ++m) FN(sample)(pl[m], pw[m], C, &k[m], v + m * C);
            SCALAR *out = feat + i * L * C + l * C;
            /* the order of hexplane.py: (s0 s1) (s2 t0) (t1 t2) */
            for (int64_t c = 0; c < C; ++c)
                out[c] = ((v[c] * v[C + c]) * (v[2 * C + c] * v[3 * C + c])) * (v[4 * C + c] * v[5 * C + c]);
        }
    }
    free(v);
}

/* Backward of hex_forward: ADDS the planes' gradients into g_planes (same layout as planes) and WRITES
 * those of p [n, 3] into g_p and of tt [n] into g_tt (NULL: not wanted). */
HOT void FN(hex_backward)(int64_t n, const SCALAR *p, const SCALAR *tt, int64_t L, const SCALAR *planes,
                      const int64_t *offsets, const int64_t *res, int64_t T, int64_t C, const SCALAR *g_feat,
                      SCALAR *g_planes, SCALAR *g_p, SCALAR *g_tt) {
    SCALAR *v = (SCALAR *)malloc(sizeof(SCALAR) * 14 * (size_t)C);
    if (!v) return;
    SCALAR *gv = v + 6 * C, *dx = gv + 6 * C, *dy = dx + C;
    static const int pairs[3][2] = {{0, 1}, {0, 2}, {1, 2}};
    for (int64_t i = 0; i < n; ++i) {
        SCALAR gq[4] = {0, 0, 0, 0};  /* x, y, z, t */
        for (int64_t l = 0; l < L; ++l) {
            const SCALAR *pl[6];
            int64_t pw[6];
            FN(Corner) k[6];
            FN(hex_level)(planes, offsets, res, T, C, l, p + 3 * i, tt[i], pl, pw, k);
            for (int m = 0; m < 6; ++m) FN(sample)(pl[m], pw[m], C, &k[m], v + m * C);
            const SCALAR *g = g_feat + i * L * C + l * C;
            /* d feat / d v_m = the product of the other five planes' samples */
#pragma GCC ivdep
            for (int64_t c = 0; c < C; ++c) {
                const SCALAR a0 = v[c], a1 = v[C + c], a2 = v[2 * C + c], a3 = v[3 * C + c], a4 = v[4 * C + c];
                const SCALAR a5 = v[5 * C + c], gc = g[c];
                const SCALAR p01 = a0 * a1, p23 = a2 * a3, p45 = a4 * a5;
                gv[c] = gc * (a1 * p23 * p45);
                gv[C + c] = gc * (a0 * p23 * p45);
                gv[2 * C + c] = gc * (p01 * a3 * p45);
                gv[3 * C + c] = gc * (p01 * a2 * p45);
                gv[4 * C + c] = gc * (p01 * p23 * a5);
                gv[5 * C + c] = gc * (p01 * p23 * a4);
            }
            for (int m = 0; m < 6; ++m) {
                const FN(Corner) *km = &k[m];
                const SCALAR fx = km->fx, fy = km->fy, *gvm = gv + m * C;
                const int64_t w = pw[m], base = (km->i0 * w + km->j0) * C;
                const SCALAR *nw = pl[m] + base;
                SCALAR *gnw = g_planes + (pl[m] - planes) + base;
                for (int64_t c = 0; c < C; ++c) dx[c] = dy[c] = (SCALAR)0;
                /* weights (1 - fx)(1 - fy), fx (1 - fy), (1 - fx) fy, fx fy and their fx, fy derivatives */
                FN(corner_bw)(C, nw, gnw, gvm, ((SCALAR)1 - fx) * ((SCALAR)1 - fy), -((SCALAR)1 - fy),
                              -((SCALAR)1 - fx), dx, dy);
                if (km->in_x) FN(corner_bw)(C, nw + C, gnw + C, gvm, fx * ((SCALAR)1 - fy), (SCALAR)1 - fy, -fx, dx, dy);
                if (km->in_y) {
                    FN(corner_bw)(C, nw + w * C, gnw + w * C, gvm, ((SCALAR)1 - fx) * fy, -fy, (SCALAR)1 - fx, dx, dy);
                    if (km->in_x) FN(corner_bw)(C, nw + w * C + C, gnw + w * C + C, gvm, fx * fy, fy, fx, dx, dy);
                }
                const SCALAR dfx = FN(chan_sum)(dx, C), dfy = FN(chan_sum)(dy, C);
                if (m < 3) {
                    gq[pairs[m][0]] += dfx * km->gx;
                    gq[pairs[m][1]] += dfy * km->gy;
                } else {
                    gq[m - 3] += dfx * km->gx;
                    gq[3] += dfy * km->gy;
                }
            }
        }
        for (int d = 0; d < 3; ++d) g_p[3 * i + d] = gq[d];
        if (g_tt) g_tt[i] = gq[3];
    }
    free(v);
}

/* HexPlane regularisers (hexplane.py, HexPlane.regularisers) of one tensor of K planes [K, C, H, W]:
 * spatial planes give the total variation 2 (mean (d_h)^2 + mean (d_w)^2) summed over the K planes; time
 * planes ([K, C, T, R], t along H) the mean squared second difference along t and the mean |1 - P|, each
 * summed over the K planes. out[0], out[1]: the two values of the kind asked (spatial: tv, 0). With grad
 * non-NULL, ADDS instead their gradients scaled by g0 and g1. Sums in double. */
HOT void FN(plane_regularisers)(const SCALAR *P, int64_t K, int64_t C, int64_t H, int64_t W, int spatial, double *out,
                            SCALAR *grad, double g0, double g1) {
    double v0 = 0.0, v1 = 0.0;
    for (int64_t k = 0; k < K; ++k) {
        const SCALAR *q = P + k * C * H * W;
        SCALAR *gq = grad ? grad + k * C * H * W : NULL;
        if (spatial) {
            const double nh = (double)(C * (H - 1) * W), nw = (double)(C * H * (W - 1));
            double sh = 0.0, sw = 0.0;
            for (int64_t c = 0; c < C; ++c)
                for (int64_t i = 0; i < H; ++i)
                    for (int64_t j = 0; j < W; ++j) {
                        const int64_t at = (c * H + i) * W + j;
                        if (i + 1 < H) {
                            const double d = (double)q[at + W] - (double)q[at];
                            if (gq) {
                                const double gd = g0 * 2.0 * 2.0 * d / nh;
                                gq[at + W] += (SCALAR)gd;
                                gq[at] -= (SCALAR)gd;
                            } else {
                                sh += d * d;
                            }
                        }
                        if (j + 1 < W) {
                            const double d = (double)q[at + 1] - (double)q[at];
                            if (gq) {
                                const double gd = g0 * 2.0 * 2.0 * d / nw;
                                gq[at + 1] += (SCALAR)gd;
                                gq[at] -= (SCALAR)gd;
                            } else {
                                sw += d * d;
                            }
                        }
                    }
            if (H > 1) v0 += 2.0 * sh / nh;
            if (W > 1) v0 += 2.0 * sw / nw;
        } else {
            const double ns = (double)(C * (H - 2) * W), nl = (double)(C * H * W);
            double ss = 0.0, sl = 0.0;
            for (int64_t c = 0; c < C; ++c)
                for (int64_t i = 0; i < H; ++i)
                    for (int64_t j = 0; j < W; ++j) {
                        const int64_t at = (c * H + i) * W + j;
                        const double one = 1.0 - (double)q[at];
                        if (gq) {
                            gq[at] -= (SCALAR)(g1 * (one > 0 ? 1.0 : (one < 0 ? -1.0 : 0.0)) / nl);
                        } else {
                            sl += fabs(one);
                        }
                        if (i + 2 < H) {
                            const double d = ((double)q[at + 2 * W] - (double)q[at + W]) - ((double)q[at + W] - (double)q[at]);
                            if (gq) {
                                const double gd = g0 * 2.0 * d / ns;
                                gq[at + 2 * W] += (SCALAR)gd;
                                gq[at + W] -= (SCALAR)(2.0 * gd);
                                gq[at] += (SCALAR)gd;
                            } else {
                                ss += d * d;
                            }
                        }
                    }
            if (H > 2) v0 += ss / ns;
            v1 += sl / nl;
        }
    }
    if (out) {
        out[0] = v0;
        out[1] = v1;
    }
}

/* ---- spherical harmonics colour (methods/gaussians/sh.py, GaussianModel.colors) ---------------------
 * colour[n, c] = max(sum_k Y_k(d) coef_k[c] + 1/2, 0) with d = (mean - centre) / |mean - centre| (the
 * norm clamped at 1e-12), k over the (degree + 1)^2 bases in the 3D-GS order and signs; coef_0 = dc[n],
 * coef_k = rest[n, k - 1] (rest holds R rows per Gaussian, of which the first (degree + 1)^2 - 1 are used). */
static inline void FN(sh_basis)(int degree, SCALAR x, SCALAR y, SCALAR z, SCALAR *Y, SCALAR (*dY)[3]) {
    const SCALAR C0 = (SCALAR)0.28209479177387814, C1 = (SCALAR)0.4886025119029199;
    const SCALAR C2[5] = {(SCALAR)1.0925484305920792, (SCALAR)-1.0925484305920792, (SCALAR)0.31539156525252005,
                          (SCALAR)-1.0925484305920792, (SCALAR)0.5462742152960396};
    const SCALAR C3[7] = {(SCALAR)-0.5900435899266435, (SCALAR)2.890611442640554, (SCALAR)-0.4570457994644658,
                          (SCALAR)0.3731763325901154, (SCALAR)-0.4570457994644658, (SCALAR)1.445305721320277,
                          (SCALAR)-0.5900435899266435};
    const SCALAR xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
    Y[0] = C0;
    if (dY) dY[0][0] = dY[0][1] = dY[0][2] = 0;
    if (degree < 1) return;
    Y[1] = -C1 * y; Y[2] = C1 * z; Y[3] = -C1 * x;
    if (dY) {
        dY[1][0] = 0; dY[1][1] = -C1; dY[1][2] = 0;
        dY[2][0] = 0; dY[2][1] = 0; dY[2][2] = C1;
        dY[3][0] = -C1; dY[3][1] = 0; dY[3][2] = 0;
    }
    if (degree < 2) return;
    Y[4] = C2[0] * xy; Y[5] = C2[1] * yz; Y[6] = C2[2] * (2 * zz - xx - yy); Y[7] = C2[3] * xz;
    Y[8] = C2[4] * (xx - yy);
    if (dY) {
        dY[4][0] = C2[0] * y; dY[4][1] = C2[0] * x; dY[4][2] = 0;
        dY[5][0] = 0; dY[5][1] = C2[1] * z; dY[5][2] = C2[1] * y;
        dY[6][0] = C2[2] * -2 * x; dY[6][1] = C2[2] * -2 * y; dY[6][2] = C2[2] * 4 * z;
        dY[7][0] = C2[3] * z; dY[7][1] = 0; dY[7][2] = C2[3] * x;
        dY[8][0] = C2[4] * 2 * x; dY[8][1] = C2[4] * -2 * y; dY[8][2] = 0;
    }
    if (degree < 3) return;
    Y[9] = C3[0] * y * (3 * xx - yy);
    Y[10] = C3[1] * xy * z;
    Y[11] = C3[2] * y * (4 * zz - xx - yy);
    Y[12] = C3[3] * z * (2 * zz - 3 * xx - 3 * yy);
    Y[13] = C3[4] * x * (4 * zz - xx - yy);
    Y[14] = C3[5] * z * (xx - yy);
    Y[15] = C3[6] * x * (xx - 3 * yy);
    if (dY) {
        dY[9][0] = C3[0] * 6 * xy; dY[9][1] = C3[0] * (3 * xx - 3 * yy); dY[9][2] = 0;
        dY[10][0] = C3[1] * yz; dY[10][1] = C3[1] * xz; dY[10][2] = C3[1] * xy;
        dY[11][0] = C3[2] * -2 * xy; dY[11][1] = C3[2] * (4 * zz - xx - 3 * yy); dY[11][2] = C3[2] * 8 * yz;
        dY[12][0] = C3[3] * -6 * xz; dY[12][1] = C3[3] * -6 * yz; dY[12][2] = C3[3] * (6 * zz - 3 * xx - 3 * yy);
        dY[13][0] = C3[4] * (4 * zz - 3 * xx - yy); dY[13][1] = C3[4] * -2 * xy; dY[13][2] = C3[4] * 8 * xz;
        dY[14][0] = C3[5] * 2 * xz; dY[14][1] = C3[5] * -2 * yz; dY[14][2] = C3[5] * (xx - yy);
        dY[15][0] = C3[6] * (3 * xx - 3 * yy); dY[15][1] = C3[6] * -6 * xy; dY[15][2] = 0;
    }
}

HOT void FN(sh_forward)(int64_t n, const SCALAR *means, const SCALAR *center, const SCALAR *dc, const SCALAR *rest,
                    int64_t R, int degree, SCALAR *out) {
    const int nb = (degree + 1) * (degree + 1);
    for (int64_t i = 0; i < n; ++i) {
        SCALAR v[3] = {means[3 * i] - center[0], means[3 * i + 1] - center[1], means[3 * i + 2] - center[2]};
        SCALAR nrm = (SCALAR)sqrt((double)(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]));
        nrm = nrm > (SCALAR)1e-12 ? nrm : (SCALAR)1e-12;
        SCALAR Y[16];
        FN(sh_basis)(degree, v[0] / nrm, v[1] / nrm, v[2] / nrm, Y, NULL);
        for (int c = 0; c < 3; ++c) {
            SCALAR acc = Y[0] * dc[3 * i + c];
            for (int k = 1; k < nb; ++k) acc += Y[k] * rest[(i * R + k - 1) * 3 + c];
            acc += (SCALAR)0.5;
            out[3 * i + c] = acc > (SCALAR)0 ? acc : (SCALAR)0;
        }
    }
}

/* Backward of sh_forward: WRITES the gradients of means [n, 3] (NULL: not wanted), dc [n, 3] and rest
 * [n, R, 3] (rows past the degree's: 0). The clamp at 0 passes the gradient where its input is >= 0. */
HOT void FN(sh_backward)(int64_t n, const SCALAR *means, const SCALAR *center, const SCALAR *dc, const SCALAR *rest,
                     int64_t R, int degree, const SCALAR *g_out, SCALAR *g_means, SCALAR *g_dc, SCALAR *g_rest) {
    const int nb = (degree + 1) * (degree + 1);
    for (int64_t i = 0; i < n; ++i) {
        SCALAR v[3] = {means[3 * i] - center[0], means[3 * i + 1] - center[1], means[3 * i + 2] - center[2]};
        SCALAR len = (SCALAR)sqrt((double)(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]));
        const SCALAR nrm = len > (SCALAR)1e-12 ? len : (SCALAR)1e-12;
        const SCALAR d[3] = {v[0] / nrm, v[1] / nrm, v[2] / nrm};
        SCALAR Y[16], dY[16][3];
        FN(sh_basis)(degree, d[0], d[1], d[2], Y, dY);
        SCALAR g[3];
        for (int c = 0; c < 3; ++c) {
            SCALAR acc = Y[0] * dc[3 * i + c];
            for (int k = 1; k < nb; ++k) acc += Y[k] * rest[(i * R + k - 1) * 3 + c];
            g[c] = acc + (SCALAR)0.5 >= (SCALAR)0 ? g_out[3 * i + c] : (SCALAR)0;
            g_dc[3 * i + c] = Y[0] * g[c];
        }
        for (int64_t k = 1; k <= R; ++k)
            for (int c = 0; c < 3; ++c) g_rest[(i * R + k - 1) * 3 + c] = k < nb ? Y[k] * g[c] : (SCALAR)0;
        if (!g_means) continue;
        SCALAR gd[3] = {0, 0, 0};  /* d loss / d direction */
        for (int k = 1; k < nb; ++k) {
            const SCALAR *cf = rest + (i * R + k - 1) * 3;
            const SCALAR gk = g[0] * cf[0] + g[1] * cf[1] + g[2] * cf[2];
            gd[0] += gk * dY[k][0];
            gd[1] += gk * dY[k][1];
            gd[2] += gk * dY[k][2];
        }
        /* d = v / max(|v|, 1e-12): (I - d d^T) / |v| where the norm is not clamped */
        const SCALAR dot = len > (SCALAR)1e-12 ? d[0] * gd[0] + d[1] * gd[1] + d[2] * gd[2] : (SCALAR)0;
        for (int c = 0; c < 3; ++c) g_means[3 * i + c] = (gd[c] - d[c] * dot) / nrm;
    }
}

/* ---- SSIM of the training loss (methods/gaussians/train.py, ssim) -----------------------------------
 * Images [H, W, C] (channels last); the separable window k[K] (symmetric, odd K) blurs with zero padding.
 * mean over channels and pixels of ((2 mx my + c1)(2 cov + c2)) / ((mx^2 + my^2 + c1)(vx + vy + c2)). */
NOINLINE static void FN(blur)(const SCALAR *restrict in, SCALAR *restrict out, SCALAR *restrict tmp, int64_t H,
                              int64_t W, const SCALAR *restrict k, int64_t K) {
    const int64_t half = K / 2;
    for (int64_t i = 0; i < H; ++i) {  /* along the columns of each row, tap by tap */
        const SCALAR *row = in + i * W;
        SCALAR *t = tmp + i * W;
        for (int64_t j = 0; j < W; ++j) t[j] = 0;
        for (int64_t q = 0; q < K; ++q) {
            const int64_t shift = q - half;  /* t[j] += k[q] row[j + shift] where 0 <= j + shift < W */
            const int64_t j0 = shift < 0 ? -shift : 0, j1 = shift > 0 ? W - shift : W;
            const SCALAR kq = k[q];
#pragma GCC ivdep
            for (int64_t j = j0; j < j1; ++j) t[j] += kq * row[j + shift];
        }
    }
    for (int64_t i = 0; i < H; ++i) {  /* then along the rows */
        SCALAR *o = out + i * W;
        for (int64_t j = 0; j < W; ++j) o[j] = 0;
        const int64_t lo = i - half < 0 ? half - i : 0, hi = i + half >= H ? H - 1 - i + half : K - 1;
        for (int64_t q = lo; q <= hi; ++q) {
            const SCALAR kq = k[q], *t = tmp + (i + q - half) * W;
#pragma GCC ivdep
            for (int64_t j = 0; j < W; ++j) o[j] += kq * t[j];
        }
    }
}

/* Returns the mean SSIM; saves the five blurred moments [5, C, H, W] (mx, my, exx, eyy, exy) in saved. */
HOT double FN(ssim_forward)(const SCALAR *x, const SCALAR *y, int64_t H, int64_t W, int64_t C, const SCALAR *k,
                        int64_t K, SCALAR *saved) {
    const int64_t HW = H * W;
    SCALAR *buf = (SCALAR *)malloc(sizeof(SCALAR) * (size_t)(2 * HW));
    if (!buf) return NAN;
    SCALAR *plane = buf, *tmp = buf + HW;
    const double c1 = 0.01 * 0.01, c2 = 0.03 * 0.03;
    double total = 0.0;
    for (int64_t c = 0; c < C; ++c) {
        SCALAR *m[5];
        for (int q = 0; q < 5; ++q) m[q] = saved + ((int64_t)q * C + c) * HW;
        for (int q = 0; q < 5; ++q) {
            const SCALAR *u = q == 1 || q == 3 ? y : x, *v = q == 0 || q == 1 ? NULL : (q == 2 ? x : y);
            for (int64_t p = 0; p < HW; ++p) plane[p] = u[p * C + c] * (v ? v[p * C + c] : (SCALAR)1);
            FN(blur)(plane, m[q], tmp, H, W, k, K);
        }
        for (int64_t p = 0; p < HW; ++p) {
            const SCALAR mx = m[0][p], my = m[1][p];
            const SCALAR vx = m[2][p] - mx * mx, vy = m[3][p] - my * my, cov = m[4][p] - mx * my;
            const SCALAR s = (((SCALAR)2 * mx * my + (SCALAR)c1) * ((SCALAR)2 * cov + (SCALAR)c2))
                             / ((mx * mx + my * my + (SCALAR)c1) * (vx + vy + (SCALAR)c2));
            total += (double)s;
        }
    }
    free(buf);
    return total / (double)(C * HW);
}

/* Backward of ssim_forward (in x only): WRITES g_x [H, W, C] = d (g mean SSIM) / d x. */
HOT void FN(ssim_backward)(const SCALAR *x, const SCALAR *y, int64_t H, int64_t W, int64_t C, const SCALAR *k, int64_t K,
                       const SCALAR *saved, double g, SCALAR *g_x) {
    const int64_t HW = H * W;
    SCALAR *buf = (SCALAR *)malloc(sizeof(SCALAR) * (size_t)(5 * HW));
    if (!buf) return;
    SCALAR *dm = buf, *de = buf + HW, *dc = buf + 2 * HW, *tmp = buf + 3 * HW, *blurred = buf + 4 * HW;
    const SCALAR c1 = (SCALAR)(0.01 * 0.01), c2 = (SCALAR)(0.03 * 0.03), scale = (SCALAR)(g / (double)(C * HW));
    for (int64_t c = 0; c < C; ++c) {
        const SCALAR *m[5];
        for (int q = 0; q < 5; ++q) m[q] = saved + ((int64_t)q * C + c) * HW;
        for (int64_t p = 0; p < HW; ++p) {
            const SCALAR mx = m[0][p], my = m[1][p];
            const SCALAR n1 = (SCALAR)2 * mx * my + c1, n2 = (SCALAR)2 * (m[4][p] - mx * my) + c2;
            const SCALAR d1 = mx * mx + my * my + c1, d2 = (m[2][p] - mx * mx) + (m[3][p] - my * my) + c2;
            const SCALAR s = (n1 * n2) / (d1 * d2);
            /* s = n1 n2 / (d1 d2): its derivatives in mx, exx and exy (the reference y has no gradient) */
            dm[p] = scale * ((SCALAR)2 * my * (n2 - n1) / (d1 * d2) - (SCALAR)2 * mx * s * ((SCALAR)1 / d1 - (SCALAR)1 / d2));
            de[p] = scale * (-s / d2);
            dc[p] = scale * ((SCALAR)2 * n1 / (d1 * d2));
        }
        /* the window is symmetric: the blur is its own transpose */
        for (int64_t p = 0; p < HW; ++p) g_x[p * C + c] = 0;
        FN(blur)(dm, blurred, tmp, H, W, k, K);
        for (int64_t p = 0; p < HW; ++p) g_x[p * C + c] += blurred[p];
        FN(blur)(de, blurred, tmp, H, W, k, K);
        for (int64_t p = 0; p < HW; ++p) g_x[p * C + c] += (SCALAR)2 * x[p * C + c] * blurred[p];
        FN(blur)(dc, blurred, tmp, H, W, k, K);
        for (int64_t p = 0; p < HW; ++p) g_x[p * C + c] += y[p * C + c] * blurred[p];
    }
    free(buf);
}
"""

COMPILE_FLAGS = ("-O3", "-shared", "-fPIC", "-std=c11", "-ffp-contract=off", "-fno-trapping-math")
"""Portable optimisation only (no ``-march=native``, no ``-ffast-math``; no fused multiply-add, and
``-fno-trapping-math`` only lets the vectoriser if-convert, every result is rounded as written): the
library gives the same numbers on every x86-64 CPU, whichever vector width runs."""

_TYPES = {torch.float32: ("float", "exp_f32", "f32"), torch.float64: ("double", "exp_f64", "f64")}


def source() -> str:
    """The whole C translation unit: the helpers, then the kernels for float and for double."""
    parts = [HEADER]
    for scalar, exp, suffix in _TYPES.values():
        parts.append(f"#define SCALAR {scalar}\n#define EXP {exp}\n#define FN(name) name##_{suffix}\n"
                     + BODY + "\n#undef SCALAR\n#undef EXP\n#undef FN\n")
    return "\n".join(parts)


def cache_folder() -> Path:
    """Where the built library is kept: ``$BENCH4D_NATIVE_CACHE``, else ``$XDG_CACHE_HOME/bench4d/native``
    (default ``~/.cache/bench4d/native``)."""
    env = os.environ.get("BENCH4D_NATIVE_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "bench4d" / "native"


def _compiler() -> Optional[str]:
    for name in (os.environ.get("CC"), "cc", "gcc", "clang"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def _build(folder: Path) -> Path:
    """Compile :func:`source` into ``folder`` (once per source, flags and compiler) and return the
    library's path. Concurrent builders each write a private file and rename it into place."""
    cc = _compiler()
    if cc is None:
        raise OSError("no C compiler (cc, gcc or clang) on PATH")
    text = source()
    try:
        version = subprocess.run([cc, "--version"], capture_output=True, text=True, timeout=60).stdout
    except (OSError, subprocess.SubprocessError) as err:
        raise OSError(f"{cc} --version failed: {err}") from err
    key = hashlib.sha256("\0".join([text, " ".join(COMPILE_FLAGS), version, sys.platform]).encode()).hexdigest()[:16]
    lib = folder / f"bench4d_raster_{key}.so"
    if lib.is_file():
        return lib
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=folder, prefix=".build-") as tmp:
        src, out = Path(tmp) / "raster.c", Path(tmp) / lib.name
        src.write_text(text)
        done = subprocess.run([cc, *COMPILE_FLAGS, "-o", str(out), str(src), "-lm"], capture_output=True, text=True,
                              timeout=300)
        if done.returncode != 0 or not out.is_file():
            raise OSError(f"{cc} failed to build the rasterizer kernels: {done.stderr.strip()[-2000:]}")
        os.replace(out, lib)
    return lib


_I64, _PTR, _F64 = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
_SIGNATURES = {
    "ssim_forward": (_F64, [_PTR, _PTR, _I64, _I64, _I64, _PTR, _I64, _PTR]),
    "ssim_backward": (None, [_PTR, _PTR, _I64, _I64, _I64, _PTR, _I64, _PTR, _F64, _PTR]),
    "sh_forward": (None, [_I64, _PTR, _PTR, _PTR, _PTR, _I64, ctypes.c_int, _PTR]),
    "sh_backward": (None, [_I64, _PTR, _PTR, _PTR, _PTR, _I64, ctypes.c_int, _PTR, _PTR, _PTR, _PTR]),
    "plane_regularisers": (None, [_PTR, _I64, _I64, _I64, _I64, ctypes.c_int, _PTR, _PTR, _F64, _F64]),
    "hex_forward": (None, [_I64, _PTR, _PTR, _I64, _PTR, _PTR, _PTR, _I64, _I64, _PTR]),
    "hex_backward": (None, [_I64, _PTR, _PTR, _I64, _PTR, _PTR, _PTR, _I64, _I64, _PTR, _PTR, _PTR, _PTR]),
    "project_forward": (None, [_I64, _PTR, _PTR, _PTR, _PTR, _PTR, _PTR, _PTR, _I64, _I64, _F64, _F64, _F64, _F64,
                               _PTR, _PTR, _PTR, _PTR, _PTR, _PTR, _PTR]),
    "project_backward": (None, [_I64, _PTR, _PTR, _PTR, _PTR, _PTR, _PTR, _PTR, _F64, _F64, _F64, _F64, _PTR, _PTR,
                                _PTR, _PTR, _PTR, _PTR]),
    "layout_bound": (_I64, [_I64, _PTR, _PTR, _I64]),
    "layout_build": (_I64, [_I64, _PTR, _PTR, _PTR, _PTR, _I64, _I64, _I64, _I64, _I64, _PTR, _PTR, _I64]),
    "forward": (_I64, [_PTR, _PTR, _PTR, _I64, _PTR, _PTR, _I64, _I64, _I64, _I64, _I64, _F64, _F64, _F64, _PTR,
                       _PTR, _PTR, _PTR, _PTR, _PTR, _PTR, _I64]),
    "backward": (ctypes.c_int, [_PTR, _PTR, _I64, _PTR, _PTR, _I64, _I64, _I64, _I64, _I64, _F64, _F64, _PTR, _PTR,
                                _PTR, _PTR, _PTR, _PTR, _PTR]),
}


def _declare(lib: ctypes.CDLL, suffix: str) -> None:
    # attribute access: ctypes caches the function object, so the declared types stick
    for name, (restype, argtypes) in _SIGNATURES.items():
        fn = getattr(lib, f"{name}_{suffix}")
        fn.restype, fn.argtypes = restype, argtypes


def _load(folder: Path) -> ctypes.CDLL:
    """The built library, loaded and declared. A cached library that does not load or lacks a kernel (a
    truncated file, another build's leftovers) is removed and built again, once."""
    path = _build(folder)
    try:
        lib = ctypes.CDLL(str(path))
        for _, _, suffix in _TYPES.values():
            _declare(lib, suffix)
        return lib
    except (OSError, AttributeError):
        path.unlink(missing_ok=True)
    lib = ctypes.CDLL(str(_build(folder)))
    for _, _, suffix in _TYPES.values():
        _declare(lib, suffix)
    return lib


_LOCK = threading.Lock()
_STATE: dict = {}


def kernels() -> Optional[ctypes.CDLL]:
    """The loaded library, building it on first use; ``None`` where it cannot be built or is switched
    off (``BENCH4D_NATIVE=0``): :func:`unavailable_reason` says why."""
    if os.environ.get("BENCH4D_NATIVE", "1").strip().lower() in ("0", "false", "no", "off"):
        return None
    with _LOCK:
        if "lib" not in _STATE:
            try:
                _STATE["lib"], _STATE["why"] = _load(cache_folder()), ""
            except (OSError, subprocess.SubprocessError, AttributeError) as err:
                _STATE["lib"], _STATE["why"] = None, str(err)
        return _STATE["lib"]


def unavailable_reason() -> str:
    """Why :func:`kernels` is ``None`` ("" when it is loaded or was not asked for yet)."""
    if os.environ.get("BENCH4D_NATIVE", "1").strip().lower() in ("0", "false", "no", "off"):
        return "switched off by BENCH4D_NATIVE=0"
    return _STATE.get("why", "")


def supports(t: Tensor) -> bool:
    """Whether the kernels take tensors like ``t`` (CPU, float32 or float64)."""
    return t.device.type == "cpu" and t.dtype in _TYPES


def _ptr(t: Optional[Tensor]) -> Optional[int]:
    return None if t is None else t.data_ptr()


@dataclass
class NativeLayout:
    """Tiles' Gaussian lists in (tile, depth) order, as compressed rows (the no-gradient part)."""

    tile_start: Tensor
    """[tiles + 1] int64: tile ``t``'s Gaussians are ``rows[tile_start[t]:tile_start[t + 1]]``."""
    rows: Tensor
    """[R] int32 Gaussian indices, front to back within each tile."""
    tiles_x: int
    tiles_y: int
    tile_size: int

    @property
    def n_rows(self) -> int:
        return int(self.rows.numel())


@torch.no_grad()
def layout(lib: ctypes.CDLL, params: Tensor, cull_q: Tensor, pixel_box: Tensor, order: Tensor, width: int,
           height: int, tile_size: int) -> NativeLayout:
    """Rows of every (tile, visible Gaussian) whose tile's pixel-centre rectangle meets the Gaussian's
    ``alpha >= alpha_min`` ellipse; ``params`` [N, 6] = (u, v, a, b, c, opacity), ``order``: the visible
    Gaussians front to back (int64)."""
    suffix = _TYPES[params.dtype][2]
    ts = int(tile_size)
    tiles_x, tiles_y = (width + ts - 1) // ts, (height + ts - 1) // ts
    params, cull_q = params.detach().contiguous(), cull_q.detach().to(params.dtype).contiguous()
    pixel_box, order = pixel_box.contiguous(), order.contiguous()
    bound = int(getattr(lib, f"layout_bound_{suffix}")(order.numel(), _ptr(order), _ptr(pixel_box), ts))
    tile_start = torch.empty(tiles_x * tiles_y + 1, dtype=torch.int64)
    rows = torch.empty(bound, dtype=torch.int32)
    total = getattr(lib, f"layout_build_{suffix}")(order.numel(), _ptr(order), _ptr(params), _ptr(cull_q),
                                                   _ptr(pixel_box), ts, tiles_x, tiles_y, width, height,
                                                   _ptr(tile_start), _ptr(rows), bound)
    if total < 0:
        raise MemoryError("the native layout kernel could not allocate its buffers")
    return NativeLayout(tile_start, rows[:total], tiles_x, tiles_y, ts)


def sigma_bound(params: Tensor, alpha_min: float) -> Tensor:
    """[N] sigma beyond which ``opacity exp(-sigma) < alpha_min`` for sure (margins keep rounding from ever
    dropping a pair that composites; -1 where the opacity itself is below ``alpha_min``): lets the kernels
    skip pixel blocks a Gaussian cannot reach."""
    o = params[:, 5].detach().double()
    bound = torch.log(o.clamp_min(alpha_min) / alpha_min) * (1 + 1e-4) + 1e-4
    return torch.where(o >= alpha_min, bound, torch.full_like(bound, -1.0)).to(params.dtype).contiguous()


class Composite(torch.autograd.Function):
    """Front-to-back compositing of ``feat`` [N, C] by the Gaussians ``params`` [N, 6] = (u, v, a, b, c,
    opacity) on a :class:`NativeLayout`. Returns (composited channels [H, W, C] without background,
    accumulated alpha [H, W])."""

    @staticmethod
    def forward(ctx, params: Tensor, feat: Tensor, lay: NativeLayout, width: int, height: int, rule,
                stats: dict):  # type: ignore[override]
        lib = kernels()
        suffix = _TYPES[params.dtype][2]
        params, feat = params.detach().contiguous(), feat.detach().contiguous()
        n, c = feat.shape
        out = torch.empty(height, width, c, dtype=feat.dtype)
        t_end = torch.empty(height, width, dtype=feat.dtype)
        last = torch.empty(height, width, dtype=torch.int32)
        contrib = torch.zeros(lay.n_rows, dtype=torch.uint8)
        smax = sigma_bound(params, rule.alpha_min)
        pairs = getattr(lib, f"forward_{suffix}")(
            _ptr(params), _ptr(smax), _ptr(feat), c, _ptr(lay.tile_start), _ptr(lay.rows), lay.tile_size, lay.tiles_x,
            lay.tiles_y, width, height, rule.alpha_min, rule.alpha_max, rule.transmittance_min,
            _ptr(out), _ptr(t_end), _ptr(last), _ptr(contrib), None, None, None, 0)
        if pairs < 0:
            raise MemoryError("the native compositing kernel could not allocate its tile buffers")
        stats["pairs"] = int(pairs)
        ctx.save_for_backward(params, feat, t_end, last, contrib)
        ctx.meta = (lay, width, height, rule)
        return out, 1.0 - t_end

    @staticmethod
    def backward(ctx, g_out: Optional[Tensor], g_acc: Optional[Tensor]):  # type: ignore[override]
        params, feat, t_end, last, contrib = ctx.saved_tensors
        lay, width, height, rule = ctx.meta
        lib = kernels()
        suffix = _TYPES[params.dtype][2]
        n, c = feat.shape
        need_params, need_feat = ctx.needs_input_grad[0], ctx.needs_input_grad[1]
        grad_params = torch.zeros(n, 6, dtype=torch.float64) if need_params else None
        grad_feat = torch.zeros(n, c, dtype=torch.float64) if need_feat else None
        g_out = None if g_out is None else g_out.to(feat.dtype).contiguous()
        g_acc = None if g_acc is None else g_acc.to(feat.dtype).contiguous()
        status = getattr(lib, f"backward_{suffix}")(
            _ptr(params), _ptr(feat), c, _ptr(lay.tile_start), _ptr(lay.rows), lay.tile_size, lay.tiles_x,
            lay.tiles_y, width, height, rule.alpha_min, rule.alpha_max, _ptr(t_end), _ptr(last), _ptr(contrib),
            _ptr(g_out), _ptr(g_acc), _ptr(grad_params), _ptr(grad_feat))
        if status != 0:
            raise MemoryError("the native compositing kernel could not allocate its tile buffers")
        return (None if grad_params is None else grad_params.to(params.dtype),
                None if grad_feat is None else grad_feat.to(feat.dtype), None, None, None, None, None)


def camera_constants(viewmat: Tensor, K: Tensor, width: int, height: int, fov_margin: float
                     ) -> tuple[Tensor, Tensor, Tensor]:
    """(view [12] = the world-to-camera rows (R | t), intrinsics [4] = (fx, fy, cx, cy), the Jacobian's
    clamp of x / z and y / z [4] = (-neg_x, pos_x, -neg_y, pos_y)), in double for the kernels."""
    view = viewmat.detach().double()[:3, :4].contiguous().reshape(-1)
    k = K.detach().double()
    fx, fy, cx, cy = (float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))
    intr = torch.tensor([fx, fy, cx, cy], dtype=torch.float64)
    lim = torch.tensor([-(cx / fx + fov_margin * (0.5 * width / fx)), (width - cx) / fx + fov_margin * (0.5 * width / fx),
                        -(cy / fy + fov_margin * (0.5 * height / fy)),
                        (height - cy) / fy + fov_margin * (0.5 * height / fy)], dtype=torch.float64)
    return view, intr, lim


class Project(torch.autograd.Function):
    """EWA projection and culling (:func:`~.torch_cpu.project_gaussians`) by the kernels: differentiable
    in means, quaternions and scales; ``(means2d [N, 2], conics [N, 3], depths [N], visible [N] bool,
    radii [N] int32, pixel_box [N, 4] int64, cull_q [N])``."""

    @staticmethod
    def forward(ctx, means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, view: Tensor, intr: Tensor,
                lim: Tensor, width: int, height: int, near: float, far: float, eps2d: float,
                alpha_min: float):  # type: ignore[override]
        lib = kernels()
        suffix = _TYPES[means.dtype][2]
        means, quats, scales, opacities = (t.detach().contiguous() for t in (means, quats, scales, opacities))
        n, dtype = means.shape[0], means.dtype
        means2d, conics = torch.empty(n, 2, dtype=dtype), torch.empty(n, 3, dtype=dtype)
        depths, cull_q = torch.empty(n, dtype=dtype), torch.empty(n, dtype=dtype)
        visible, radii = torch.empty(n, dtype=torch.bool), torch.empty(n, dtype=torch.int32)
        box = torch.empty(n, 4, dtype=torch.int64)
        getattr(lib, f"project_forward_{suffix}")(
            n, _ptr(means), _ptr(quats), _ptr(scales), _ptr(opacities), _ptr(view), _ptr(intr), _ptr(lim), width,
            height, near, far, eps2d, alpha_min, _ptr(means2d), _ptr(conics), _ptr(depths), _ptr(visible),
            _ptr(radii), _ptr(box), _ptr(cull_q))
        ctx.save_for_backward(means, quats, scales, opacities)
        ctx.meta = (view, intr, lim, near, far, eps2d, alpha_min)
        ctx.mark_non_differentiable(visible, radii, box, cull_q)
        return means2d, conics, depths, visible, radii, box, cull_q

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, *_):  # type: ignore[override]
        means, quats, scales, opacities = ctx.saved_tensors
        view, intr, lim, near, far, eps2d, alpha_min = ctx.meta
        lib = kernels()
        suffix = _TYPES[means.dtype][2]
        n, dtype = means.shape[0], means.dtype
        grads = [None if g is None else g.to(dtype).contiguous() for g in (g_means2d, g_conics, g_depths)]
        g_means, g_quats, g_scales = torch.empty(n, 3, dtype=dtype), torch.empty(n, 4, dtype=dtype), \
            torch.empty(n, 3, dtype=dtype)
        getattr(lib, f"project_backward_{suffix}")(
            n, _ptr(means), _ptr(quats), _ptr(scales), _ptr(opacities), _ptr(view), _ptr(intr), _ptr(lim), near,
            far, eps2d, alpha_min, *(_ptr(g) for g in grads), _ptr(g_means), _ptr(g_quats), _ptr(g_scales))
        return (g_means, g_quats, g_scales) + (None,) * 10


@torch.no_grad()
def blend_weights(params: Tensor, lay: NativeLayout, width: int, height: int, rule,
                  n_pairs: int) -> tuple[Tensor, Tensor, Tensor]:
    """Every composited pair of a render on ``lay`` (``n_pairs`` of them, as its forward counted):
    ([P] int64 flat pixel index, [P] int64 Gaussian, [P] weight alpha T) -- with the geometry frozen,
    rendering any channels is this sparse linear map."""
    lib = kernels()
    suffix = _TYPES[params.dtype][2]
    params = params.detach().contiguous()
    n = params.shape[0]
    feat = params.new_zeros(n, 1)
    out, t_end = params.new_empty(height, width, 1), params.new_empty(height, width)
    last = torch.empty(height, width, dtype=torch.int32)
    pix, gid = torch.empty(n_pairs, dtype=torch.int64), torch.empty(n_pairs, dtype=torch.int32)
    weight = params.new_empty(n_pairs)
    contrib = torch.zeros(lay.n_rows, dtype=torch.uint8)  # held here: the kernel writes into it
    smax = sigma_bound(params, rule.alpha_min)
    got = getattr(lib, f"forward_{suffix}")(
        _ptr(params), _ptr(smax), _ptr(feat), 1, _ptr(lay.tile_start), _ptr(lay.rows), lay.tile_size, lay.tiles_x,
        lay.tiles_y, width, height, rule.alpha_min, rule.alpha_max, rule.transmittance_min, _ptr(out), _ptr(t_end),
        _ptr(last), _ptr(contrib), _ptr(pix), _ptr(gid), _ptr(weight), n_pairs)
    if got != n_pairs:
        raise RuntimeError(f"the native kernels counted {got} composited pairs, expected {n_pairs}")
    return pix, gid.long(), weight


class HexPlaneSample(torch.autograd.Function):
    """The HexPlane's multi-resolution features (:meth:`methods.gaussians.hexplane.HexPlane.forward` after
    the normalisation) by the kernels: ``p`` [N, 3] plane coordinates in [-1, 1], ``tt`` [N] time
    coordinates, then per level its spatial planes [3, C, R, R] and time planes [3, C, T, R]. Returns
    [N, levels * C]; differentiable in ``p``, ``tt`` and every plane."""

    @staticmethod
    def forward(ctx, p: Tensor, tt: Tensor, *planes: Tensor):  # type: ignore[override]
        lib = kernels()
        suffix = _TYPES[p.dtype][2]
        levels = len(planes) // 2
        c, t = planes[0].shape[1], planes[1].shape[2]
        res = torch.tensor([planes[2 * l].shape[2] for l in range(levels)], dtype=torch.int64)
        # channels last: a sample's C values are one contiguous run
        flat = [pl.detach().permute(0, 2, 3, 1).reshape(-1) for pl in planes]
        offsets = torch.tensor([0] + [f.numel() for f in flat], dtype=torch.int64).cumsum(0)[:-1].contiguous()
        packed = torch.cat(flat)
        p, tt = p.detach().contiguous(), tt.detach().contiguous()
        n = p.shape[0]
        feat = p.new_empty(n, levels * c)
        getattr(lib, f"hex_forward_{suffix}")(n, _ptr(p), _ptr(tt), levels, _ptr(packed), _ptr(offsets), _ptr(res),
                                              t, c, _ptr(feat))
        ctx.save_for_backward(p, tt, packed, offsets, res)
        ctx.meta = (levels, c, t, [tuple(pl.shape) for pl in planes])
        return feat

    @staticmethod
    def backward(ctx, g_feat: Tensor):  # type: ignore[override]
        p, tt, packed, offsets, res = ctx.saved_tensors
        levels, c, t, shapes = ctx.meta
        lib = kernels()
        suffix = _TYPES[p.dtype][2]
        n = p.shape[0]
        g_feat = g_feat.to(p.dtype).contiguous()
        g_packed = torch.zeros_like(packed)
        g_p = p.new_empty(n, 3)
        g_tt = p.new_empty(n) if ctx.needs_input_grad[1] else None
        getattr(lib, f"hex_backward_{suffix}")(n, _ptr(p), _ptr(tt), levels, _ptr(packed), _ptr(offsets),
                                               _ptr(res), t, c, _ptr(g_feat), _ptr(g_packed), _ptr(g_p), _ptr(g_tt))
        grads = []
        for i, shape in enumerate(shapes):
            start = int(offsets[i])
            size = shape[0] * shape[1] * shape[2] * shape[3]
            k, ch, h, w = shape
            grads.append(g_packed[start:start + size].view(k, h, w, ch).permute(0, 3, 1, 2).contiguous())
        return (g_p if ctx.needs_input_grad[0] else None, g_tt, *grads)


class PlaneRegularisers(torch.autograd.Function):
    """:meth:`methods.gaussians.hexplane.HexPlane.regularisers` by the kernels: ``(plane_tv,
    time_smoothness, l1_time_planes)`` of the spatial planes (the first ``n_spatial`` tensors) and the
    time planes (the rest), each tensor [3, C, H, W]."""

    @staticmethod
    def forward(ctx, n_spatial: int, *planes: Tensor):  # type: ignore[override]
        lib = kernels()
        suffix = _TYPES[planes[0].dtype][2]
        fn = getattr(lib, f"plane_regularisers_{suffix}")
        sums = [0.0, 0.0, 0.0]
        out = torch.zeros(2, dtype=torch.float64)
        kept = [pl.detach().contiguous() for pl in planes]
        for i, pl in enumerate(kept):
            spatial = i < n_spatial
            fn(_ptr(pl), *pl.shape, int(spatial), _ptr(out), None, 0.0, 0.0)
            if spatial:
                sums[0] += float(out[0])
            else:
                sums[1] += float(out[0])
                sums[2] += float(out[1])
        # kept on ctx, not saved: each of the three terms may be differentiated on its own (the planes are
        # the module's parameters, alive anyway)
        ctx.planes = kept
        ctx.n_spatial = n_spatial
        dtype = planes[0].dtype
        return tuple(torch.tensor(v, dtype=dtype) for v in sums)

    @staticmethod
    def backward(ctx, g_tv: Tensor, g_smooth: Tensor, g_l1: Tensor):  # type: ignore[override]
        planes = ctx.planes
        lib = kernels()
        suffix = _TYPES[planes[0].dtype][2]
        fn = getattr(lib, f"plane_regularisers_{suffix}")
        grads = []
        for i, pl in enumerate(planes):
            g = torch.zeros_like(pl)
            if i < ctx.n_spatial:
                fn(_ptr(pl), *pl.shape, 1, None, _ptr(g), float(g_tv), 0.0)
            else:
                fn(_ptr(pl), *pl.shape, 0, None, _ptr(g), float(g_smooth), float(g_l1))
            grads.append(g)
        return (None, *grads)


class ShColor(torch.autograd.Function):
    """3D-GS view-dependent colour (:meth:`methods.gaussians.model.GaussianModel.colors`) by the kernels:
    ``max(SH_degree(normalise(means - centre)) + 0.5, 0)`` from ``sh_dc`` [N, 1, 3] and ``sh_rest``
    [N, R, 3]; differentiable in ``means``, ``sh_dc`` and ``sh_rest``."""

    @staticmethod
    def forward(ctx, means: Tensor, center: Tensor, sh_dc: Tensor, sh_rest: Tensor,
                degree: int):  # type: ignore[override]
        lib = kernels()
        suffix = _TYPES[means.dtype][2]
        means, sh_dc, sh_rest = (t.detach().contiguous() for t in (means, sh_dc, sh_rest))
        center = center.detach().to(means.dtype).reshape(3).contiguous()
        n = means.shape[0]
        out = means.new_empty(n, 3)
        getattr(lib, f"sh_forward_{suffix}")(n, _ptr(means), _ptr(center), _ptr(sh_dc), _ptr(sh_rest),
                                             sh_rest.shape[1], int(degree), _ptr(out))
        ctx.save_for_backward(means, center, sh_dc, sh_rest)
        ctx.degree = int(degree)
        return out

    @staticmethod
    def backward(ctx, g_out: Tensor):  # type: ignore[override]
        means, center, sh_dc, sh_rest = ctx.saved_tensors
        lib = kernels()
        suffix = _TYPES[means.dtype][2]
        g_out = g_out.to(means.dtype).contiguous()
        g_means = torch.empty_like(means) if ctx.needs_input_grad[0] else None
        g_dc, g_rest = torch.empty_like(sh_dc), torch.empty_like(sh_rest)
        getattr(lib, f"sh_backward_{suffix}")(means.shape[0], _ptr(means), _ptr(center), _ptr(sh_dc), _ptr(sh_rest),
                                              sh_rest.shape[1], ctx.degree, _ptr(g_out), _ptr(g_means), _ptr(g_dc),
                                              _ptr(g_rest))
        return g_means, None, g_dc, g_rest, None


class Ssim(torch.autograd.Function):
    """Mean SSIM of two [H, W, C] images (:func:`methods.gaussians.train.ssim`: zero-padded separable
    Gaussian window, K1 = 0.01, K2 = 0.03) by the kernels; differentiable in ``img`` only."""

    @staticmethod
    def forward(ctx, img: Tensor, ref: Tensor, window: Tensor):  # type: ignore[override]
        lib = kernels()
        suffix = _TYPES[img.dtype][2]
        img, ref = img.detach().contiguous(), ref.detach().to(img.dtype).contiguous()
        window = window.detach().to(img.dtype).contiguous()
        h, w, c = img.shape
        saved = img.new_empty(5, c, h, w)
        value = getattr(lib, f"ssim_forward_{suffix}")(_ptr(img), _ptr(ref), h, w, c, _ptr(window), window.numel(),
                                                       _ptr(saved))
        ctx.save_for_backward(img, ref, window, saved)
        return img.new_tensor(value)

    @staticmethod
    def backward(ctx, g: Tensor):  # type: ignore[override]
        img, ref, window, saved = ctx.saved_tensors
        lib = kernels()
        suffix = _TYPES[img.dtype][2]
        h, w, c = img.shape
        g_img = torch.empty_like(img)
        getattr(lib, f"ssim_backward_{suffix}")(_ptr(img), _ptr(ref), h, w, c, _ptr(window), window.numel(),
                                                _ptr(saved), float(g), _ptr(g_img))
        return g_img, None, None
