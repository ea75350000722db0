"""The particle detector's compiled arithmetic (numba, ``cache=True``): the background's block statistics
and bilinear maps, hot pixels, local maxima, each candidate's connected pixels above the threshold, the
Gaussian fits of overlapping images (rendering the others, the three-point fits, the 3 x 3 shape fit,
Levenberg-Marquardt of an elongated image as one ellipse or two round images) and the ridge test.

These kernels are THE implementation: :mod:`ari_sfm.particles.background` and
:mod:`ari_sfm.particles.detect` call them (their docstrings say what each step means). They compute in
float64 (float32 where the image is), and live in one module (numba's cache is invalidated by the source
file of the function it compiled).
"""
from __future__ import annotations

import math

import numpy as np

from ..kernel_cache import njit  # numba's njit, the kernels compiled into the wheel read first

_JIT = dict(cache=True, nogil=True, error_model="numpy")

MAD_SCALE = 1.4826  # a Gaussian's standard deviation per median absolute deviation


# --------------------------------------------------------------------------- background


@njit(**_JIT)
def _kth_key(keys, n, k, count):
    """The k-th smallest (0-based) of keys[:n] (uint32) by radix selection, 8 bits a pass from the top:
    each pass counts the candidates left by their next byte and keeps the byte holding the k-th."""
    prefix = np.uint32(0)
    mask = np.uint32(0)
    for shift in (24, 16, 8, 0):
        sh = np.uint32(shift)
        count[:] = 0
        for i in range(n):
            if keys[i] & mask == prefix:
                count[(keys[i] >> sh) & np.uint32(255)] += 1
        c = 0
        d = 0
        while c + count[d] <= k:
            c += count[d]
            d += 1
        k -= c
        prefix |= np.uint32(d) << sh
        mask |= np.uint32(255) << sh
        if count[d] == 1:  # one candidate left: it is the k-th
            for i in range(n):
                if keys[i] & mask == prefix:
                    return keys[i]
    return prefix


@njit(**_JIT)
def _median(a, n, keys, count):
    """The median of a[:n] (float32; the mean of the middle two for an even n), exact, by radix selection
    on the floats' bits made unsigned-ordered; ``keys`` (>= n, uint32) and ``count`` (256) are scratch."""
    bits = a[:n].view(np.uint32)
    for i in range(n):
        b = bits[i]
        keys[i] = ~b if b & np.uint32(0x80000000) else b | np.uint32(0x80000000)
    middle = np.empty(2, np.uint32)
    middle[0] = _kth_key(keys, n, n // 2, count)
    middle[1] = _kth_key(keys, n, n // 2 - 1, count) if n % 2 == 0 else middle[0]
    for j in range(2):
        key = middle[j]
        middle[j] = key & np.uint32(0x7FFFFFFF) if key & np.uint32(0x80000000) else ~key
    value = middle.view(np.float32)
    return 0.5 * (float(value[0]) + float(value[1]))


@njit(**_JIT)
def block_statistics(img, opened, y0, x0, by, bx, step, quantum, clip_sigmas, clip_floor, clipped_factor,
                     high_pass_gain):
    """Per block: the median of the residual over the opening, and the noise.

    The noise: the standard deviation of each pixel minus the mean of its four neighbours (the border
    pixel standing for the one beyond), within ``clip_sigmas`` robust sigmas or ``clip_floor`` quanta of
    the median, per unit pixel noise and floored at the quantisation's.

    Args:
        img: The image (h, w), float32.
        opened: Its grey opening (h, w).
        y0: (ny,) first row of each block.
        x0: (nx,) first column of each block.
        by: Block height (px).
        bx: Block width (px).
        step: Every ``step``-th pixel along rows and columns is sampled.
        quantum: The grey level step (0 for float images).
        clip_sigmas: Clip at this many robust sigmas ...
        clip_floor: ... or at least this many quanta.
        clipped_factor: The std of a unit Gaussian clipped at ``clip_sigmas`` (the clipped std is divided by it).
        high_pass_gain: The noise of the high-pass per unit pixel noise (divided out).

    Returns:
        (ny, nx) float32 medians and (ny, nx) float32 noises.
    """
    h, w = img.shape
    ny, nx = len(y0), len(x0)
    med_out = np.empty((ny, nx), np.float32)
    noise_out = np.empty((ny, nx), np.float32)
    rows = np.arange(0, by, step)
    cols = np.arange(0, bx, step)
    m = len(rows) * len(cols)
    res = np.empty(m, np.float32)
    diff = np.empty(m, np.float32)
    dev = np.empty(m, np.float32)
    floor = max(quantum / math.sqrt(12.0), 1e-6)
    keys = np.empty(m, np.uint32)
    counts = np.zeros(256, np.int64)
    for i in range(ny):
        for j in range(nx):
            k = 0
            for r in rows:
                y = y0[i] + r
                yu = max(y - 1, 0)  # the border reflected as OpenCV's BORDER_REFLECT: its own pixel
                yd = min(y + 1, h - 1)
                for c in cols:
                    x = x0[j] + c
                    xl = max(x - 1, 0)
                    xr = min(x + 1, w - 1)
                    res[k] = img[y, x] - opened[y, x]
                    diff[k] = np.float32(img[y, x] - np.float32(0.25) * (img[yu, x] + img[yd, x] + img[y, xl]
                                                                         + img[y, xr]))
                    k += 1
            med_out[i, j] = _median(res, m, keys, counts)
            med = _median(diff, m, keys, counts)
            for q in range(m):
                dev[q] = abs(diff[q] - med)
            mad = MAD_SCALE * _median(dev, m, keys, counts)
            robust = clip_sigmas * mad >= clip_floor * quantum
            half = clip_sigmas * mad if robust else clip_floor * quantum
            count = 0
            total = 0.0
            for q in range(m):
                if abs(diff[q] - med) <= half:
                    count += 1
                    total += diff[q]
            mean = total / max(count, 1)
            var = 0.0
            for q in range(m):
                if abs(diff[q] - med) <= half:
                    var += (diff[q] - mean) ** 2
            std = math.sqrt(var / max(count - 1, 1)) / (clipped_factor if robust else 1.0)
            noise_out[i, j] = max(std / high_pass_gain, floor)
    return med_out, noise_out


@njit(**_JIT)
def _axis_weights(n, centres):
    """Bilinear weights along one axis: for each of ``n`` pixels the lower block index and the upper
    block's weight (constant beyond the first and last centres)."""
    lo = np.empty(n, np.int64)
    wt = np.empty(n, np.float32)
    m = len(centres)
    k = 0
    for p in range(n):
        if m == 1 or p <= centres[0]:
            lo[p], wt[p] = 0, 0.0
            continue
        if p >= centres[m - 1]:
            lo[p], wt[p] = m - 2, 1.0
            continue
        while centres[k + 1] < p:
            k += 1
        lo[p] = k
        wt[p] = (p - centres[k]) / (centres[k + 1] - centres[k])
    return lo, wt


@njit(**_JIT)
def level_and_noise(opened, block_median, block_noise, cy, cx, read_var, gain, floor_var):
    """The background level and noise per pixel.

    Args:
        opened: The image's grey opening (h, w).
        block_median: (ny, nx) the blocks' medians of the residual, added to ``opened`` (bilinear).
        block_noise: (ny, nx) the blocks' noise (bilinear).
        cy: (ny,) the block centres' rows.
        cx: (nx,) the block centres' columns.
        read_var: The sensor model's read noise variance.
        gain: Its variance per grey level.
        floor_var: The least variance of the sensor model.

    Returns:
        (h, w) float32 level, and (h, w) float32 noise: the larger of the sensor model
        sqrt(read_var + gain x level) (at least sqrt(floor_var)) and the blocks' noise.
    """
    h, w = opened.shape
    ylo, ywt = _axis_weights(h, cy)
    xlo, xwt = _axis_weights(w, cx)
    ny, nx = block_median.shape
    level = np.empty((h, w), np.float32)
    noise = np.empty((h, w), np.float32)
    row_med = np.empty(nx)
    row_noise = np.empty(nx)
    for y in range(h):
        i0 = ylo[y]
        i1 = min(i0 + 1, ny - 1)
        fy = ywt[y]
        for j in range(nx):  # the blocks' values interpolated to this row
            row_med[j] = (1 - fy) * block_median[i0, j] + fy * block_median[i1, j]
            row_noise[j] = (1 - fy) * block_noise[i0, j] + fy * block_noise[i1, j]
        for x in range(w):
            j0 = xlo[x]
            j1 = min(j0 + 1, nx - 1)
            fx = xwt[x]
            lv = opened[y, x] + np.float32((1 - fx) * row_med[j0] + fx * row_med[j1])
            level[y, x] = lv
            bn = (1 - fx) * row_noise[j0] + fx * row_noise[j1]
            noise[y, x] = max(math.sqrt(max(read_var + gain * lv, floor_var)), bn)
    return level, noise


# --------------------------------------------------------------------------- pixels


@njit(**_JIT)
def without_hot_pixels(res, noise, limit):
    """Replace hot pixels by the median of their 8 neighbours.

    A hot pixel is sharper along u and along v than an optical image can be: the log curvature
    2 ln I0 - ln I-1 - ln I+1 above ``limit`` on both axes, i.e. I0^2 > e^limit I-1 I+1 (intensities
    floored at the noise).

    Args:
        res: The residual over the background (h, w), float32.
        noise: The noise (h, w).
        limit: The log curvature limit.

    Returns:
        A copy of ``res`` with the hot pixels replaced.
    """
    h, w = res.shape
    out = res.copy()
    vals = np.empty(8, np.float32)
    ratio = math.exp(limit)
    for y in range(1, h - 1):
        for x in range(1, w - 1):
            c = max(float(res[y, x]), max(float(noise[y, x]), 1e-6))
            c2 = c * c
            left = max(float(res[y, x - 1]), max(float(noise[y, x - 1]), 1e-6))
            right = max(float(res[y, x + 1]), max(float(noise[y, x + 1]), 1e-6))
            if c2 <= ratio * left * right:
                continue
            up = max(float(res[y - 1, x]), max(float(noise[y - 1, x]), 1e-6))
            down = max(float(res[y + 1, x]), max(float(noise[y + 1, x]), 1e-6))
            if c2 <= ratio * up * down:
                continue
            k = 0
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    if dy or dx:
                        vals[k] = res[y + dy, x + dx]
                        k += 1
            s = np.sort(vals)
            out[y, x] = np.float32(0.5) * (s[3] + s[4])
    return out


@njit(**_JIT)
def local_maxima(smooth, noise, factor, floor):
    """Local maxima above the threshold.

    Of a plateau of equal values, the pixels with no plateau pixel above or to the left are taken.

    Args:
        smooth: The smoothed residual (h, w), float32.
        noise: The noise (h, w).
        factor: The threshold in noise sigmas.
        floor: The threshold in grey levels.

    Returns:
        (rows, cols) int64 of the pixels off the border at the maximum of their 3 x 3 neighbourhood and at
        least max(``factor`` x noise, ``floor``).
    """
    h, w = smooth.shape
    ys = np.empty(h * w // 4 + 16, np.int64)
    xs = np.empty(h * w // 4 + 16, np.int64)
    n = 0
    hmax = np.empty((3, w), np.float32)  # the maxima of three along each of the rows y - 1, y, y + 1

    def row_max(r, out):
        out[0] = max(r[0], r[1])
        for x in range(1, w - 1):
            out[x] = max(max(r[x - 1], r[x]), r[x + 1])
        out[w - 1] = max(r[w - 2], r[w - 1])

    row_max(smooth[0], hmax[0])
    row_max(smooth[1], hmax[1])
    for y in range(1, h - 1):
        a, b, c = (y - 1) % 3, y % 3, (y + 1) % 3
        row_max(smooth[y + 1], hmax[c])
        ha, hb, hc = hmax[a], hmax[b], hmax[c]
        up, row = smooth[y - 1], smooth[y]
        for x in range(1, w - 1):
            s0 = row[x]
            if s0 < max(max(ha[x], hb[x]), hc[x]):  # not the maximum of its 3 x 3 (most pixels)
                continue
            if not (s0 > up[x - 1] and s0 > up[x] and s0 > up[x + 1] and s0 > row[x - 1]):
                continue  # a plateau's pixel with another above or to the left
            if s0 < floor or s0 < np.float32(factor * noise[y, x]):
                continue
            if n == len(ys):
                ys = np.concatenate((ys, np.empty(len(ys), np.int64)))
                xs = np.concatenate((xs, np.empty(len(xs), np.int64)))
            ys[n] = y
            xs[n] = x
            n += 1
    return ys[:n], xs[:n]


@njit(**_JIT)
def connected_regions(clean, noise, factor, floor, ys, xs, max_count):
    """Measure each candidate's region of pixels above the threshold.

    A region: the pixels 4-connected to the candidate's brightest pixel of the 3 x 3 around (ys, xs) and
    above max(``factor`` x noise, ``floor``). Candidates in one region share it.

    Args:
        clean: The residual without hot pixels (h, w).
        noise: The noise (h, w).
        factor: The threshold in noise sigmas.
        floor: The threshold in grey levels.
        ys: (N,) int64 the candidates' rows.
        xs: (N,) int64 their columns.
        max_count: A region beyond this many pixels is counted no further (its count is max_count + 1, its
            widths and sum those of the pixels counted).

    Returns:
        Per candidate (N,): the pixel count, the widths along u and v (bounding box), the grey sum
        (``clean`` over the region), and the brightest pixel of the 3 x 3.
    """
    h, w = clean.shape
    n = len(ys)
    count = np.zeros(n, np.int64)
    width_u = np.zeros(n, np.int64)
    width_v = np.zeros(n, np.int64)
    total = np.zeros(n, np.float64)
    peak = np.zeros(n, np.float64)
    label = np.zeros(h * w, np.int32)  # 0: not reached; else the region's number + 1
    reg_count = np.zeros(n + 1, np.int64)
    reg_wu = np.zeros(n + 1, np.int64)
    reg_wv = np.zeros(n + 1, np.int64)
    reg_sum = np.zeros(n + 1)
    stack = np.empty(4096, np.int64)
    regions = 0
    for k in range(n):
        sy, sx = ys[k], xs[k]
        best = -np.inf
        for dy in range(-1, 2):
            for dx in range(-1, 2):
                y, x = ys[k] + dy, xs[k] + dx
                if 0 <= y < h and 0 <= x < w and clean[y, x] > best:
                    best, sy, sx = clean[y, x], y, x
        peak[k] = best
        if best < max(factor * noise[sy, sx], floor):
            continue
        seed = sy * w + sx
        lab = label[seed]
        if lab == 0:
            regions += 1
            lab = regions
            label[seed] = lab
            stack[0] = seed
            top = 1
            c, tot = 0, 0.0
            u0 = u1 = sx
            v0 = v1 = sy
            while top:
                top -= 1
                p = stack[top]
                y, x = p // w, p % w
                if c <= max_count:
                    c += 1
                    tot += clean[y, x]
                    u0, u1 = min(u0, x), max(u1, x)
                    v0, v1 = min(v0, y), max(v1, y)
                if top + 4 > len(stack):
                    stack = np.concatenate((stack, np.empty(len(stack), np.int64)))
                if x > 0 and label[p - 1] == 0 and clean[y, x - 1] >= max(factor * noise[y, x - 1], floor):
                    label[p - 1] = lab
                    stack[top] = p - 1
                    top += 1
                if x < w - 1 and label[p + 1] == 0 and clean[y, x + 1] >= max(factor * noise[y, x + 1], floor):
                    label[p + 1] = lab
                    stack[top] = p + 1
                    top += 1
                if y > 0 and label[p - w] == 0 and clean[y - 1, x] >= max(factor * noise[y - 1, x], floor):
                    label[p - w] = lab
                    stack[top] = p - w
                    top += 1
                if y < h - 1 and label[p + w] == 0 and clean[y + 1, x] >= max(factor * noise[y + 1, x], floor):
                    label[p + w] = lab
                    stack[top] = p + w
                    top += 1
            reg_count[lab], reg_wu[lab], reg_wv[lab], reg_sum[lab] = c, u1 - u0 + 1, v1 - v0 + 1, tot
        count[k], width_u[k], width_v[k], total[k] = reg_count[lab], reg_wu[lab], reg_wv[lab], reg_sum[lab]
    return count, width_u, width_v, total, peak


# --------------------------------------------------------------------------- Gaussian images


@njit(**_JIT)
def render(model, prev_cx, prev_cy, u, v, A, su, sv, r):
    """Draw the images' Gaussians into the model, in place.

    Each Gaussian A exp(-(x-u)^2 / 2 su^2 - (y-v)^2 / 2 sv^2) is drawn over the (2 r + 1)^2 pixels
    around its nearest pixel, in the order of the images, after the windows drawn before are set to zero:
    the same sums as a fresh array.

    Args:
        model: (h, w) float64, updated.
        prev_cx: The previous windows' centre columns.
        prev_cy: Their centre rows.
        u: (N,) centres along u.
        v: (N,) centres along v.
        A: (N,) peaks.
        su: (N,) sigmas along u.
        sv: (N,) sigmas along v.
        r: The windows' half-width (px).

    Returns:
        The windows' centres (cx, cy), each (N,) int64.
    """
    h, w = model.shape
    for k in range(len(prev_cx)):
        for y in range(max(prev_cy[k] - r, 0), min(prev_cy[k] + r + 1, h)):
            for x in range(max(prev_cx[k] - r, 0), min(prev_cx[k] + r + 1, w)):
                model[y, x] = 0.0
    n = len(u)
    cxs = np.empty(n, np.int64)
    cys = np.empty(n, np.int64)
    gx = np.empty(2 * r + 1)
    gy = np.empty(2 * r + 1)
    for k in range(n):
        cx, cy = int(np.rint(u[k])), int(np.rint(v[k]))
        cxs[k], cys[k] = cx, cy
        for t in range(2 * r + 1):
            gx[t] = math.exp(-((cx - r + t - u[k]) ** 2) / (2.0 * su[k] ** 2))
            gy[t] = A[k] * math.exp(-((cy - r + t - v[k]) ** 2) / (2.0 * sv[k] ** 2))
        for a in range(2 * r + 1):
            y = cy - r + a
            if y < 0 or y >= h:
                continue
            for b in range(2 * r + 1):
                x = cx - r + b
                if 0 <= x < w:
                    model[y, x] += gy[a] * gx[b]
    return cxs, cys


@njit(inline="always", **_JIT)
def _own(res, model, y, x, u, v, A, su, sv):
    """The residual at (y, x) minus the other images' Gaussians (the model minus this image's own)."""
    val = float(res[y, x])
    if model.shape[0]:
        g = A * math.exp(-((x - u) ** 2 / (2.0 * su * su) + (y - v) ** 2 / (2.0 * sv * sv)))
        val -= model[y, x] - g
    return val


@njit(**_JIT)
def own_pixels(res, model, y0, x0, u, v, A, su, sv, dy, dx):
    """Each image's own pixels: the residual minus the other images' Gaussians.

    Args:
        res: The residual (h, w).
        model: The sum of all images' Gaussians (h, w); shape (0, 0): none.
        y0: (N,) each image's peak row.
        x0: (N,) its peak column.
        u: (N,) its Gaussian's centre along u.
        v: (N,) along v.
        A: (N,) its peak.
        su: (N,) its sigma along u.
        sv: (N,) along v.
        dy: (M,) row offsets of the pixels taken.
        dx: (M,) column offsets.

    Returns:
        (N, M) the pixels (y0 + dy, x0 + dx), clamped to the frame, minus the other images' Gaussians.
    """
    h, w = res.shape
    n, m = len(y0), len(dy)
    out = np.empty((n, m))
    for k in range(n):
        for j in range(m):
            y = min(max(y0[k] + dy[j], 0), h - 1)
            x = min(max(x0[k] + dx[j], 0), w - 1)
            out[k, j] = _own(res, model, y, x, u[k], v[k], A[k], su[k], sv[k])
    return out


@njit(inline="always", **_JIT)
def _log_parabola(lm, l0, lp):
    """Vertex offset, curvature and vertex height of the parabola through (-1, lm), (0, l0), (1, lp)."""
    b = 0.5 * (lp - lm)
    c = 0.5 * (lp - 2.0 * l0 + lm)
    return -b / (2.0 * c), c, l0 - b * b / (4.0 * c)


@njit(**_JIT)
def fit_round(res, model, anchor_y, anchor_x, y0, x0, u, v, A, su, sv, saturated, fixed, sigma, s_lo, s_hi,
              centroid_r, min_signal, max_log_overshoot):
    """One round of three-point Gaussian fits along u and v of each image's own pixels, in place.

    A flat top (saturated) or a failed fit: the centroid of its own pixels above half their peak within
    ``centroid_r``. The peak pixel follows the centre, at most one pixel from its anchor.

    Args:
        res: The residual (h, w).
        model: The sum of all images' Gaussians (h, w); shape (0, 0): none.
        anchor_y: (N,) the row each image started from.
        anchor_x: (N,) its column.
        y0: (N,) peak rows, updated.
        x0: (N,) peak columns, updated.
        u: (N,) centres along u, updated.
        v: (N,) centres along v, updated.
        A: (N,) peaks, updated.
        su: (N,) sigmas along u, updated.
        sv: (N,) sigmas along v, updated.
        saturated: (N,) bool: a flat top, centred by its centroid.
        fixed: (N,) bool: keeps its values.
        sigma: The hint's sigma (px), for failed fits.
        s_lo: Smallest fitted sigma (px).
        s_hi: Largest fitted sigma (px).
        centroid_r: The centroid's window half-width (px).
        min_signal: Floor of the intensities before their log.
        max_log_overshoot: A fitted peak is at most e^this times its peak pixel.
    """
    h, w = res.shape
    sdy = (0, 0, 0, -1, 1)
    sdx = (0, -1, 1, 0, 0)
    lg = np.empty(5)
    own = np.empty(5)
    nc = 2 * centroid_r + 1
    pb = np.empty(nc * nc)
    for k in range(len(y0)):
        if fixed[k]:
            continue
        for j in range(5):
            yy = min(max(y0[k] + sdy[j], 0), h - 1)
            xx = min(max(x0[k] + sdx[j], 0), w - 1)
            own[j] = _own(res, model, yy, xx, u[k], v[k], A[k], su[k], sv[k])
            lg[j] = math.log(max(own[j], min_signal))
        ou, cu, tu = _log_parabola(lg[1], lg[0], lg[2])
        ov, cv, tv = _log_parabola(lg[3], lg[0], lg[4])
        good = cu < 0 and cv < 0 and math.isfinite(ou) and math.isfinite(ov) and not saturated[k]
        if good:
            nu = x0[k] + min(max(ou, -1.0), 1.0)
            nv = y0[k] + min(max(ov, -1.0), 1.0)
            nsu = min(max(math.sqrt(-0.5 / cu), s_lo), s_hi)
            nsv = min(max(math.sqrt(-0.5 / cv), s_lo), s_hi)
            nA = math.exp(min(0.5 * (tu + tv), lg[0] + max_log_overshoot))
        else:
            nsu = nsv = sigma
            nA = max(own[0], min_signal)
            top = -np.inf
            q = 0
            for a in range(-centroid_r, centroid_r + 1):
                for b in range(-centroid_r, centroid_r + 1):
                    yy = min(max(y0[k] + a, 0), h - 1)
                    xx = min(max(x0[k] + b, 0), w - 1)
                    pb[q] = _own(res, model, yy, xx, u[k], v[k], A[k], su[k], sv[k])
                    top = max(top, pb[q])
                    q += 1
            tot = su_ = sv_ = 0.0
            q = 0
            for a in range(-centroid_r, centroid_r + 1):
                for b in range(-centroid_r, centroid_r + 1):
                    wt = pb[q] if pb[q] >= 0.5 * top else 0.0
                    tot += wt
                    su_ += wt * b
                    sv_ += wt * a
                    q += 1
            tot = max(tot, min_signal)
            nu = x0[k] + su_ / tot
            nv = y0[k] + sv_ / tot
        y0[k] = min(max(int(np.rint(nv)), max(anchor_y[k] - 1, 1)), min(anchor_y[k] + 1, h - 2))
        x0[k] = min(max(int(np.rint(nu)), max(anchor_x[k] - 1, 1)), min(anchor_x[k] + 1, w - 2))
        u[k], v[k], A[k], su[k], sv[k] = nu, nv, nA, nsu, nsv


@njit(**_JIT)
def _solve(M, b):
    """x with M x = b (small, square; Gaussian elimination with partial pivoting). M and b are copied."""
    n = M.shape[0]
    a = M.copy()
    x = b.copy()
    for c in range(n):
        p = c
        for r in range(c + 1, n):
            if abs(a[r, c]) > abs(a[p, c]):
                p = r
        if p != c:
            for j in range(n):
                a[c, j], a[p, j] = a[p, j], a[c, j]
            for j in range(x.shape[1]):
                x[c, j], x[p, j] = x[p, j], x[c, j]
        for r in range(c + 1, n):
            f = a[r, c] / a[c, c]
            for j in range(c, n):
                a[r, j] -= f * a[c, j]
            for j in range(x.shape[1]):
                x[r, j] -= f * x[c, j]
    for c in range(n - 1, -1, -1):
        for j in range(x.shape[1]):
            s = x[c, j]
            for k in range(c + 1, n):
                s -= a[c, k] * x[k, j]
            x[c, j] = s / a[c, c]
    return x


@njit(**_JIT)
def shape_hessians(own, noise, model_noise):
    """Fit a quadratic to each image's log intensities by weighted least squares.

    Weights: (I / noise)^2 with a ``model_noise`` relative floor; intensities floored at half the noise.

    Args:
        own: (N, 9) each image's 3 x 3 pixels, row-major around the peak pixel.
        noise: (N,) the noise at each peak pixel.
        model_noise: The relative noise floor per pixel.

    Returns:
        (N, 3) the Hessians (h_uu, h_uv, h_vv) and (N, 3, 3) their covariances.
    """
    n = own.shape[0]
    hess = np.empty((n, 3))
    cov = np.empty((n, 3, 3))
    design = np.empty((9, 6))
    q = 0
    for dy in range(-1, 2):
        for dx in range(-1, 2):
            design[q, 0], design[q, 1], design[q, 2] = 1.0, dx, dy
            design[q, 3], design[q, 4], design[q, 5] = 0.5 * dx * dx, dx * dy, 0.5 * dy * dy
            q += 1
    normal = np.empty((6, 6))
    rhs = np.zeros((6, 4))
    for k in range(n):
        nz = max(noise[k], 1e-9)
        normal[:] = 0.0
        rhs[:] = 0.0
        for q in range(9):
            intensity = max(own[k, q], 0.5 * nz)
            wt = 1.0 / ((nz / intensity) ** 2 + model_noise ** 2)
            lg = math.log(intensity)
            for i in range(6):
                rhs[i, 0] += wt * lg * design[q, i]
                for j in range(6):
                    normal[i, j] += wt * design[q, i] * design[q, j]
        rhs[3, 1] = rhs[4, 2] = rhs[5, 3] = 1.0
        sol = _solve(normal, rhs)
        rhs[3, 1] = rhs[4, 2] = rhs[5, 3] = 0.0
        for i in range(3):
            hess[k, i] = sol[3 + i, 0]
            for j in range(3):
                cov[k, i, j] = sol[3 + i, 1 + j]
    return hess, cov


# --------------------------------------------------------------------------- elongated images


@njit(inline="always", **_JIT)
def _ellipse(q, X, Y, m, J):
    """One elliptical Gaussian (u, v, A, a, c, b: A exp(-(a dx^2 + 2 b dx dy + c dy^2) / 2)) at X, Y into
    m (P,) and its Jacobian J (P, 6); NaN where (a, b, c) is no ellipse (a step outside, refused)."""
    a, c, b = q[3], q[4], q[5]
    proper = a > 0 and c > 0 and a * c > b * b
    for p in range(len(X)):
        ex, ey = X[p] - q[0], Y[p] - q[1]
        g = math.exp(-0.5 * max(a * ex * ex + 2.0 * b * ex * ey + c * ey * ey, 0.0)) if proper else np.nan
        mv = q[2] * g
        m[p] = mv
        J[p, 0] = mv * (a * ex + b * ey)
        J[p, 1] = mv * (b * ex + c * ey)
        J[p, 2] = g
        J[p, 3] = -0.5 * mv * ex * ex
        J[p, 4] = -0.5 * mv * ey * ey
        J[p, 5] = -mv * ex * ey


@njit(inline="always", **_JIT)
def _pair(q, X, Y, m, J):
    """Two round Gaussians (u1, v1, u2, v2, A1, A2, sigma) at X, Y into m (P,) and J (P, 7)."""
    s2 = q[6] ** 2
    for p in range(len(X)):
        ex1, ey1 = X[p] - q[0], Y[p] - q[1]
        ex2, ey2 = X[p] - q[2], Y[p] - q[3]
        g1 = math.exp(-(ex1 ** 2 + ey1 ** 2) / (2 * s2))
        g2 = math.exp(-(ex2 ** 2 + ey2 ** 2) / (2 * s2))
        m1, m2 = q[4] * g1, q[5] * g2
        m[p] = m1 + m2
        J[p, 0] = m1 * ex1 / s2
        J[p, 1] = m1 * ey1 / s2
        J[p, 2] = m2 * ex2 / s2
        J[p, 3] = m2 * ey2 / s2
        J[p, 4] = g1
        J[p, 5] = g2
        J[p, 6] = (m1 * (ex1 ** 2 + ey1 ** 2) + m2 * (ex2 ** 2 + ey2 ** 2)) / (s2 * q[6])


@njit(inline="always", **_JIT)
def _evaluate(kind, q, X, Y, data, m, J, r):
    """The model (0: ellipse, 1: pair) at q: residuals into r, Jacobian into J; returns the cost (inf
    unless every residual is finite)."""
    if kind == 0:
        _ellipse(q, X, Y, m, J)
    else:
        _pair(q, X, Y, m, J)
    cost = 0.0
    for p in range(len(X)):
        r[p] = data[p] - m[p]
        cost += r[p] * r[p]
    return cost if math.isfinite(cost) else np.inf


@njit(**_JIT)
def levenberg_marquardt(kind, params, X, Y, data, iterations, tolerance):
    """Fit a model to each image's pixels by Levenberg-Marquardt.

    Damping 1e-2, x 0.3 on a better step, x 10 on a worse; a fit stops once its cost falls by less than
    ``tolerance`` of itself or the damping reaches 1e8.

    Args:
        kind: 0: one elliptical Gaussian (u, v, A, a, c, b); 1: two round ones (u1, v1, u2, v2, A1, A2,
            sigma).
        params: (N, K) each fit's start.
        X: (N, P) the pixels' columns.
        Y: (N, P) their rows.
        data: (N, P) the pixels' values.
        iterations: Steps per fit at most.
        tolerance: Relative cost decrease below which a fit stops.

    Returns:
        (N, K) the fitted parameters and (N,) each fit's sum of squared residuals (inf where the start is
        no model).
    """
    n, k = params.shape
    P = X.shape[1]
    out = params.copy()
    costs = np.empty(n)
    m = np.empty(P)
    J = np.empty((P, k))
    r = np.empty(P)
    Jt_ = np.empty((P, k))
    r_t = np.empty(P)
    damped = np.empty((k, k))
    g = np.empty((k, 1))
    trial = np.empty(k)
    for i in range(n):
        p = out[i]
        lam = 1e-2
        cost = _evaluate(kind, p, X[i], Y[i], data[i], m, J, r)
        if not math.isfinite(cost):  # no model at the start (no ellipse): no step can be taken or judged
            costs[i] = cost
            continue
        for _ in range(iterations):
            # J^T J (symmetric: the upper triangle, mirrored) and J^T r in one pass over the pixels
            for a in range(k):
                g[a, 0] = 0.0
                for b in range(a, k):
                    damped[a, b] = 0.0
            for t in range(P):
                for a in range(k):
                    ja = J[t, a]
                    g[a, 0] += ja * r[t]
                    for b in range(a, k):
                        damped[a, b] += ja * J[t, b]
            ok = True
            for a in range(k):
                for b in range(a + 1, k):
                    damped[b, a] = damped[a, b]
                damped[a, a] += lam * (damped[a, a] + 1e-9)
            for a in range(k):
                for b in range(k):
                    if not math.isfinite(damped[a, b]):
                        ok = False
            if ok:
                step = _solve(damped, g)
                for a in range(k):
                    trial[a] = p[a] + step[a, 0]
            else:
                for a in range(k):
                    trial[a] = p[a]
            cost_t = _evaluate(kind, trial, X[i], Y[i], data[i], m, Jt_, r_t)
            better = cost_t < cost
            settled = False
            if better:
                settled = cost - cost_t <= tolerance * cost
                p[:] = trial
                r[:] = r_t
                J[:] = Jt_
                cost = cost_t
                lam = max(lam * 0.3, 1e-9)
            else:
                lam = min(lam * 10.0, 1e9)
            if settled or lam >= 1e8:
                break
        costs[i] = cost
    return out, costs


# --------------------------------------------------------------------------- ridges


@njit(**_JIT)
def on_ridge(res, noise_at, u, v, A, axis, r, level, support_sigmas, min_signal):
    """Which images lie on a ridge (a streak, a blob's rim).

    An image is on a ridge when, along its widest axis or one of u, v and the two diagonals, the residual
    at the nearest pixels on both sides stays above ``level`` of its peak at r px and half that at 2 r px.

    Args:
        res: The residual (h, w).
        noise_at: (N,) the noise at each image.
        u: (N,) centres along u.
        v: (N,) centres along v.
        A: (N,) peaks.
        axis: (N, 2) each image's widest axis (unit vector, u v).
        r: The distance (px).
        level: The fraction of the peak.
        support_sigmas: Noise sigmas allowed.
        min_signal: Floor of the peak.

    Returns:
        (N,) bool.
    """
    h, w = res.shape
    c = 1.0 / math.sqrt(2.0)
    du = np.array([1.0, 0.0, c, c, 0.0])
    dv = np.array([0.0, 1.0, c, -c, 0.0])
    out = np.zeros(len(u), np.bool_)
    for k in range(len(u)):
        du[4], dv[4] = axis[k, 0], axis[k, 1]
        margin = support_sigmas * noise_at[k]
        peak = max(A[k], min_signal)
        for d in range(5):
            ridge = True
            for step, lev in ((1, level), (2, 0.5 * level)):
                dist = step * r
                lo = np.inf
                for sign in (-1.0, 1.0):
                    x = min(max(int(np.rint(u[k] + sign * dist * du[d])), 0), w - 1)
                    y = min(max(int(np.rint(v[k] + sign * dist * dv[d])), 0), h - 1)
                    lo = min(lo, res[y, x])
                if not lo - margin >= lev * peak:
                    ridge = False
                    break
            if ridge:
                out[k] = True
                break
    return out
