"""Compiled inner loops of the sonar model (numba).

The loops that dominate a frame's cost, written once as plain loops: sampling the reflectors, the
occlusion test of every echo's ray against every wall and circle (with an early exit at the first
blocker), and the accumulation of each echo's separable point-spread function into the image. The
NumPy versions spent most of their time building (rays x blockers) and (echoes x bins) temporaries
(3.2 ms a frame before, BENCHMARKS.md).
Compiled on first use and cached on disk next to this file when it is writable.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _blocked(sx, sy, px, py, seg_a, seg_b, skip_seg, circ_c, circ_r, skip_circ):
    """Does a wall or circle other than the ray's own reflector cut the ray s -> p before p?
    Tolerances keep a reflector's own surface from blocking it."""
    dx, dy = px - sx, py - sy
    for j in range(seg_a.shape[0]):
        if j == skip_seg:
            continue
        ex, ey = seg_b[j, 0] - seg_a[j, 0], seg_b[j, 1] - seg_a[j, 1]
        den = dx * ey - dy * ex
        if abs(den) <= 1e-12:
            continue
        wx, wy = seg_a[j, 0] - sx, seg_a[j, 1] - sy
        t = (wx * ey - wy * ex) / den  # along the ray
        u = (wx * dy - wy * dx) / den  # along the wall
        if t > 1e-6 and t < 1 - 1e-4 and u >= 0 and u <= 1:
            return True
    L = np.sqrt(dx * dx + dy * dy)
    inv = 1.0 / max(L, 1e-12)
    ux, uy = dx * inv, dy * inv
    for j in range(circ_c.shape[0]):
        if j == skip_circ:
            continue
        ox, oy = circ_c[j, 0] - sx, circ_c[j, 1] - sy
        proj = ux * ox + uy * oy
        perp2 = ox * ox + oy * oy - proj * proj
        r2 = circ_r[j] * circ_r[j]
        if perp2 < r2:
            entry = proj - np.sqrt(r2 - perp2)
            if entry > 1e-6 and entry < L - 1e-4:
                return True
    return False


@njit(cache=True, nogil=True)
def _keep(out, m, f, sx, sy, heading, qx, qy, amp, r_max, seg_a, seg_b, skip_seg, circ_c, circ_r, skip_circ,
          source, along):
    """Append reflector point q to ``out`` if it is in front of the sensor, in range and unoccluded."""
    rx, ry = qx - sx, qy - sy
    r = np.sqrt(rx * rx + ry * ry)
    theta = np.arctan2(ry, rx) - heading
    theta = (theta + np.pi) % (2 * np.pi) - np.pi
    if abs(theta) < np.pi / 2 and r < r_max and r > 1e-3 and amp > 0 and \
            not _blocked(sx, sy, qx, qy, seg_a, seg_b, skip_seg, circ_c, circ_r, skip_circ):
        out[m, 0], out[m, 1], out[m, 2], out[m, 3], out[m, 4], out[m, 5] = f, r, theta, amp, source, along
        return m + 1
    return m


@njit(cache=True, nogil=True)
def reflector_echoes(sensors, seg_a, seg_b, seg_refl, circ_c, circ_r, circ_refl, r_max, wall_step,
                     specular_n, wall_gain):
    """Unoccluded reflector points seen from each sensor pose (x, y, heading): rows of
    (frame, range, azimuth, amplitude before directivity and absorption, reflector, position),
    frame by frame. The reflector is wall j (j) or circle j (n_walls + j); the position is the
    sample's distance from the wall's start (0 for a circle).

    Walls are sampled every ``wall_step`` where they come within ``r_max``; each sample reflects
    with a cos^n specular lobe and 1/(2r) spreading (an image source). A circle of radius a reflects
    at the point facing the sensor, with sqrt(a) / (2 r^1.5) (cylinder backscatter).
    """
    n_seg, n_circ = seg_a.shape[0], circ_c.shape[0]
    cap = 16
    for _ in range(n_seg):  # the most samples one frame can take of each wall
        cap += int(2 * r_max / wall_step) + 2
    out = np.empty((sensors.shape[0] * (cap + n_circ), 6))
    m = 0
    for f in range(sensors.shape[0]):
        sx, sy, heading = sensors[f, 0], sensors[f, 1], sensors[f, 2]
        for j in range(n_seg):
            ex, ey = seg_b[j, 0] - seg_a[j, 0], seg_b[j, 1] - seg_a[j, 1]
            length = np.sqrt(ex * ex + ey * ey)
            ux, uy = ex / length, ey / length
            relx, rely = sx - seg_a[j, 0], sy - seg_a[j, 1]
            foot = relx * ux + rely * uy
            dperp = abs(relx * uy - rely * ux)
            if not dperp < r_max:
                continue
            h = np.sqrt(max(r_max * r_max - dperp * dperp, 0.0))
            lo, hi = max(0.0, foot - h), min(length, foot + h)
            count = max(int(np.floor((hi - lo) / wall_step + 0.5)), 0)
            for k in range(count):
                t = lo + (k + 0.5) * wall_step
                qx, qy = seg_a[j, 0] + t * ux, seg_a[j, 1] + t * uy
                tx, ty = sx - qx, sy - qy
                dist = np.sqrt(tx * tx + ty * ty)
                cos_inc = abs(tx * -uy + ty * ux) / max(dist, 1e-9)
                amp = seg_refl[j] * cos_inc ** specular_n / (2 * max(dist, 1e-3)) * wall_gain
                m = _keep(out, m, f, sx, sy, heading, qx, qy, amp, r_max, seg_a, seg_b, j, circ_c, circ_r, -1, j, t)
        for j in range(n_circ):
            ox, oy = circ_c[j, 0] - sx, circ_c[j, 1] - sy
            dc = np.sqrt(ox * ox + oy * oy)
            a = circ_r[j]
            if dc - a < r_max and dc > a:
                qx, qy = circ_c[j, 0] - a * ox / dc, circ_c[j, 1] - a * oy / dc
                amp = circ_refl[j] * np.sqrt(a) / (2 * max(dc - a, 1e-3) ** 1.5)
                m = _keep(out, m, f, sx, sy, heading, qx, qy, amp, r_max, seg_a, seg_b, -1, circ_c, circ_r, j,
                          n_seg + j, 0.0)
    return out[:m].copy()


@njit(cache=True, nogil=True)
def accumulate_psf_coherence(out, out3, out_mic, frame, r, u, amp2, r_c, range_step, offsets, renv2, r0, r_step,
                             u_c, beam2, beam3_2, u_step, u3_max):
    """out[f, i, a] += amp2 * renv2(r_c[i] - r) * beam2(u_c[a] - u) for every echo (frame f, range r,
    u = sin azimuth): delay-and-sum, both PSFs looked up in their finely tabulated form, range only
    near the echo. In the same pass the echoes' energy through the DMAS3 pattern (``out3``, only
    within ``u3_max`` of the echo, ``u_c`` ascending; u3_max < 0: none) and their energy at one
    microphone, which has no azimuth pattern (``out_mic[f, i]``): the coherence factor's denominator."""
    n_range, n_az = out.shape[1], out.shape[2]
    row = np.empty(n_az)
    row3 = np.empty(n_az)
    for n in range(r.shape[0]):
        a_lo, a_hi = 0, n_az
        if u3_max < 0.0:
            a_hi = 0
        elif u3_max < 2.0:
            a_lo = np.searchsorted(u_c, u[n] - u3_max)
            a_hi = np.searchsorted(u_c, u[n] + u3_max, side="right")
        for a in range(n_az):
            row[a] = beam2[int(np.rint((u_c[a] - u[n] + 2.0) / u_step))] * amp2[n]
        for a in range(a_lo, a_hi):
            row3[a] = beam3_2[int(np.rint((u_c[a] - u[n] + 2.0) / u_step))] * amp2[n]
        i0 = int(np.floor((r[n] - r_c[0]) / range_step))
        f = frame[n]
        for k in offsets:
            i = i0 + k
            if i < 0 or i >= n_range:
                continue
            ir = int(np.rint((r_c[i] - r[n] - r0) / r_step))
            if ir < 0 or ir >= renv2.shape[0]:
                continue
            w = renv2[ir]
            out_mic[f, i] += w * amp2[n]
            for a in range(n_az):
                out[f, i, a] += w * row[a]
            for a in range(a_lo, a_hi):
                out3[f, i, a] += w * row3[a]


@njit(cache=True, nogil=True)
def coherence_amplitude(e, e3, e_mic, noise, has_noise, dmas3_noise, mic_noise):
    """DMAS3 x coherence factor, in place in ``e3`` (F, R, A), from the echoes' delay-and-sum energy
    ``e``, DMAS3 energy ``e3`` and per-microphone energy ``e_mic`` (F, R), plus the noise field
    ``noise`` (F, R, A; read only if ``has_noise``): delay-and-sum hears it whole, DMAS3
    ``dmas3_noise`` times weaker, one microphone ``mic_noise[f]`` (N sigma^2) on average.
    CF <= 1 by Cauchy-Schwarz; float rounding of the tabulated PSFs can nudge it over."""
    for f in range(e.shape[0]):
        for i in range(e.shape[1]):
            inv = 1.0 / max(e_mic[f, i] + mic_noise[f], 1e-30)
            for a in range(e.shape[2]):
                n = noise[f, i, a] if has_noise else 0.0
                cf = min((e[f, i, a] + n) * inv, 1.0)
                e3[f, i, a] = np.sqrt(e3[f, i, a] + dmas3_noise * n) * cf


@njit(cache=True, nogil=True)
def arc_clearance(x, y, th, v, w, dt, steps, seg_a, seg_b, circ_c, circ_r):
    """Smallest distance to any wall or circle surface of the poses reached by driving (v, w) for
    ``steps`` steps of ``dt`` (exact unicycle arcs, as robot.integrate)."""
    best = np.inf
    for _ in range(steps):
        if abs(w) < 1e-9:
            x, y = x + v * dt * np.cos(th), y + v * dt * np.sin(th)
        else:
            th2 = th + w * dt
            x, y = x + v / w * (np.sin(th2) - np.sin(th)), y - v / w * (np.cos(th2) - np.cos(th))
            th = th2
        for j in range(seg_a.shape[0]):
            ax, ay = seg_a[j, 0], seg_a[j, 1]
            ex, ey = seg_b[j, 0] - ax, seg_b[j, 1] - ay
            t = ((x - ax) * ex + (y - ay) * ey) / max(ex * ex + ey * ey, 1e-12)
            t = min(max(t, 0.0), 1.0)
            dx, dy = x - ax - t * ex, y - ay - t * ey
            best = min(best, np.sqrt(dx * dx + dy * dy))
        for j in range(circ_c.shape[0]):
            dx, dy = x - circ_c[j, 0], y - circ_c[j, 1]
            best = min(best, np.sqrt(dx * dx + dy * dy) - circ_r[j])
    return best
