"""Fit a spinning LiDAR's beam table, laser offsets and azimuth resolution from its points
(docs/attacks.md, "Fitting the sensor model").

A scan holds no labels of which laser produced a point, but every return of laser ``k`` lies on
its cone: seen from the sensor origin at horizontal distance ``d``, its elevation ``phi`` obeys
``tan(phi) = tan(theta_k) + c_k / d``, with ``c_k`` the laser's height above the origin (0 on a
single-origin sensor). The fit:

1. **Single-origin table** from the data: peaks of a fine elevation histogram (as many as there
   are beams; gaps left by beams without returns are split), refined by 1-D Lloyd iterations
   (each point to its nearest beam, each beam to the median of its points).
2. **Laser offsets** (``offsets="auto"`` or ``"on"``): a Hough transform over ``(c, tan theta)``
   (every distinct (range, elevation) cell votes once per candidate ``c``, so a ground ring seen
   at one range cannot outvote a laser seen at many) gives each laser's start; alternating
   nearest-beam assignment and per-laser line fits of ``tan(phi)`` against ``1 / d`` refine it.
   A laser whose points span too few ranges to show parallax takes the median offset of its
   neighbours in the table. ``"auto"`` keeps the offsets only when they put clearly more points
   on their beams than the single-origin table.
3. **Report** (:func:`fit_report`): share of points near their beam, per-beam residuals and
   warnings when the origin looks wrong.
4. **Azimuth bins** (:func:`estimate_azimuth_bins`): the firing step from the azimuth gaps
   between neighbouring returns of one beam in one frame.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from pcdet_atlas.ops.lidar_presets import waymo_top_inclinations_deg

__all__ = [
    "BeamFit",
    "FitReport",
    "fit_beam_table",
    "fit_report",
    "estimate_azimuth_bins",
    "KNOWN_FAN_DEG",
]

#: Points nearer the sensor axis than this are not used by the fit (m).
_MIN_HORIZ_M = 1.0
#: Fine elevation histogram bin of the single-origin initialisation (rad).
_HIST_BIN_RAD = math.radians(0.005)
#: Hough grid: candidate laser heights (m) and tan-elevation bin.
_HOUGH_C_MAX_M, _HOUGH_C_STEP_M = 0.5, 0.005
_HOUGH_T_BIN = math.radians(0.02)
#: Distinct-cell quantisation of the Hough votes: log-range step and tan-elevation step.
_CELL_LOG_RANGE, _CELL_T = 0.01, math.radians(0.005)
#: At most this many distinct cells vote (evenly strided), and a laser needs this many votes.
_HOUGH_MAX_CELLS, _HOUGH_MIN_VOTES = 60_000, 3.0
#: A laser's points must span at least this much of 1 / d (1/m) for its own offset.
_MIN_PARALLAX_SPAN = 0.02
#: "auto" keeps the offsets when they raise the on-beam share by at least this much.
_AUTO_GAIN = 0.02
#: A point is *on* its beam within this fraction of the local beam spacing.
ON_BEAM_FRACTION = 0.25
#: Elevation span (deg) of the widest known sensor presets, widened by the warning margin.
KNOWN_FAN_DEG = (-30.67, 10.67)
_FAN_MARGIN_DEG = 10.0
#: Warnings: on-beam share below this, or a median laser height beyond this (m).
_MIN_ON_BEAM_SHARE = 0.8
_MAX_MEDIAN_OFFSET_M = 0.3


@dataclass
class BeamFit:
    """A fitted table: ``(B,)`` ascending elevations (rad), ``(B,)`` laser heights (m) or
    ``None``, and the number of beams that received no points (placed between the others)."""

    inclinations: np.ndarray
    offsets: np.ndarray | None
    empty_beams: int = 0


def _geometry(points_xyz: np.ndarray, origin: Sequence[float]):
    """Horizontal distance ``d`` and elevation ``phi`` (float64) of the usable points."""
    pts = np.asarray(points_xyz, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"points must have shape (N, 3+), got {pts.shape}")
    rel = pts[:, :3] - np.asarray(origin, dtype=np.float64)
    finite = np.isfinite(rel).all(axis=1)
    rel = rel[finite]
    d = np.hypot(rel[:, 0], rel[:, 1])
    keep = d >= _MIN_HORIZ_M
    return d[keep], np.arctan2(rel[keep, 2], d[keep])


def _smooth(h: np.ndarray, sigma_bins: float) -> np.ndarray:
    half = max(1, int(3 * sigma_bins))
    k = np.exp(-0.5 * (np.arange(-half, half + 1) / sigma_bins) ** 2)
    return np.convolve(h, k / k.sum(), mode="same")


def _pick_peaks(profile: np.ndarray, count: int, min_sep_bins: int) -> np.ndarray:
    """Indices of up to ``count`` highest local maxima at least ``min_sep_bins`` apart."""
    inner = (profile[1:-1] > profile[:-2]) & (profile[1:-1] >= profile[2:]) & (profile[1:-1] > 0)
    cand = np.nonzero(inner)[0] + 1
    cand = cand[np.argsort(-profile[cand], kind="stable")]
    chosen: list[int] = []
    taken = np.zeros(profile.size, dtype=bool)
    for i in cand.tolist():
        if not taken[i]:
            chosen.append(i)
            taken[max(0, i - min_sep_bins + 1) : i + min_sep_bins] = True
            if len(chosen) == count:
                break
    return np.sort(np.asarray(chosen, dtype=np.int64))


def _fill(centers: np.ndarray, count: int) -> np.ndarray:
    """Split the widest gaps until there are ``count`` centres (beams the data never saw)."""
    centers = np.sort(centers)
    while centers.size < count:
        if centers.size < 2:
            raise ValueError(f"the points show fewer than 2 beams; cannot fit {count}")
        j = int(np.argmax(np.diff(centers)))
        centers = np.insert(centers, j + 1, (centers[j] + centers[j + 1]) / 2)
    return centers


def _lloyd(phi: np.ndarray, centers: np.ndarray, iterations: int = 30) -> np.ndarray:
    """1-D Lloyd: nearest beam, then each beam to the median of its points (empty beams stay)."""
    for _ in range(iterations):
        beam = np.searchsorted((centers[1:] + centers[:-1]) / 2, phi)
        new = centers.copy()
        order = np.argsort(beam, kind="stable")
        bounds = np.searchsorted(beam[order], np.arange(centers.size + 1))
        for b in range(centers.size):
            if bounds[b + 1] > bounds[b]:
                new[b] = np.median(phi[order[bounds[b] : bounds[b + 1]]])
        new = np.sort(new)
        if np.allclose(new, centers, atol=1e-10, rtol=0):
            return new
        centers = new
    return centers


def _single_origin(phi: np.ndarray, num_beams: int, init: str) -> tuple[np.ndarray, int]:
    if init == "default_table":
        return _lloyd(phi, np.deg2rad(waymo_top_inclinations_deg(num_beams))), 0
    if init != "data":
        raise ValueError(f"init must be 'data' or 'default_table', got {init!r}")
    lo, hi = float(phi.min()), float(phi.max())
    nbins = int((hi - lo) / _HIST_BIN_RAD) + 3
    hist = np.bincount(((phi - lo) / _HIST_BIN_RAD).astype(np.int64) + 1, minlength=nbins)
    q_lo, q_hi = np.quantile(phi, [0.001, 0.999])
    min_sep = max(2, int(0.25 * (q_hi - q_lo) / max(num_beams - 1, 1) / _HIST_BIN_RAD))
    peaks = _pick_peaks(_smooth(hist.astype(np.float64), 1.5), num_beams, min_sep)
    centers = lo + (peaks - 1 + 0.5) * _HIST_BIN_RAD
    empty = num_beams - centers.size
    return _lloyd(phi, _fill(centers, num_beams)), empty


def _line_fit(x: np.ndarray, t: np.ndarray, c_prior: float) -> tuple[float, float]:
    """``(T, c)`` of ``t = T + c x``: least squares when the points span enough of ``x`` to
    show parallax, else ``c_prior`` and the median intercept."""
    if x.size >= 3 and np.ptp(x) >= _MIN_PARALLAX_SPAN:
        slope, icpt = np.polyfit(x, t, 1)
        if abs(slope) <= 2 * _HOUGH_C_MAX_M:
            return float(icpt), float(slope)
    return float(np.median(t - c_prior * x)), c_prior


def _hough_start(
    d: np.ndarray, phi: np.ndarray, num_beams: int, tol: float
) -> tuple[np.ndarray, np.ndarray]:
    """Start ``(tan theta, c)`` per laser from a ``(c, tan theta)`` Hough accumulator, one laser
    at a time: take the strongest cell, fit its line, remove its points' votes (so neither a
    found laser's wings nor a horizontal surface its points lie on can be taken again)."""
    t, x = np.tan(phi), 1.0 / d
    cell = np.stack([np.floor(np.log(d) / _CELL_LOG_RANGE), np.floor(t / _CELL_T)], axis=1).astype(
        np.int64
    )
    _, first = np.unique(cell, axis=0, return_index=True)
    first = first[:: max(1, math.ceil(first.size / _HOUGH_MAX_CELLS))]
    t, x = t[first], x[first]  # one vote per distinct (range, elevation) cell
    cs = np.arange(-_HOUGH_C_MAX_M, _HOUGH_C_MAX_M + _HOUGH_C_STEP_M / 2, _HOUGH_C_STEP_M)
    lo = float(t.min()) - _HOUGH_C_MAX_M * float(x.max()) - _HOUGH_T_BIN
    hi = float(t.max()) + _HOUGH_C_MAX_M * float(x.max()) + _HOUGH_T_BIN
    nt = int((hi - lo) / _HOUGH_T_BIN) + 2
    flat = (np.arange(cs.size)[:, None] * nt).astype(np.int64) + (
        (t[None, :] - cs[:, None] * x[None, :] - lo) / _HOUGH_T_BIN
    ).astype(np.int64)  # (C, U) accumulator cell of each vote
    acc = np.bincount(flat.ravel(), minlength=cs.size * nt).astype(np.float64)
    alive = np.ones(t.size, dtype=bool)
    starts: list[tuple[float, float]] = []
    while len(starts) < num_beams:
        grid = acc.reshape(cs.size, nt)
        smooth = grid.copy()
        smooth[:, 1:-1] = (grid[:, :-2] + 2 * grid[:, 1:-1] + grid[:, 2:]) / 4
        r, j = np.unravel_index(int(np.argmax(smooth)), smooth.shape)
        if smooth[r, j] < _HOUGH_MIN_VOTES:
            break
        tan0, c0 = lo + (j + 0.5) * _HOUGH_T_BIN, float(cs[r])
        near = alive & (np.abs(t - tan0 - c0 * x) < 2 * _HOUGH_T_BIN + _HOUGH_C_STEP_M * x)
        for _ in range(3):
            if not near.any():
                break
            tan0, c0 = _line_fit(x[near], t[near], c0)
            near = alive & (np.abs(t - tan0 - c0 * x) < tol)
        if not near.any():
            acc[r * nt + j] = 0  # an isolated cell: drop it
            continue
        starts.append((tan0, c0))
        acc -= np.bincount(flat[:, near].ravel(), minlength=acc.size)
        alive &= ~near
    found = np.asarray(starts, dtype=np.float64).reshape(-1, 2)
    return found[:, 0], found[:, 1]


def _assign(d, phi, tan_k, c_k):
    """Nearest beam at each point's distance and the residual (rad), chunked."""
    beams, res = [], []
    for s in range(0, d.size, 65536):
        pred = np.arctan(tan_k[None, :] + c_k[None, :] / d[s : s + 65536, None])  # (n, B)
        diff = phi[s : s + 65536, None] - pred
        b = np.abs(diff).argmin(axis=1)
        beams.append(b)
        res.append(diff[np.arange(b.size), b])
    return np.concatenate(beams), np.concatenate(res)


def _local_spacing(incl: np.ndarray) -> np.ndarray:
    """``(B,)`` mean spacing to each beam's neighbours (rad)."""
    gaps = np.diff(incl)
    return np.concatenate([[gaps[0]], (gaps[1:] + gaps[:-1]) / 2, [gaps[-1]]])


def _refine_offsets(d, phi, tan_k, c_k, iterations: int = 12):
    """Alternate nearest-beam assignment and per-laser line fits ``tan phi = T + c / d``."""
    t, x = np.tan(phi), 1.0 / d
    for _ in range(iterations):
        order = np.argsort(tan_k, kind="stable")
        tan_k, c_k = tan_k[order], c_k[order]
        beam, res = _assign(d, phi, tan_k, c_k)
        tol = 0.5 * _local_spacing(np.arctan(tan_k))[beam]
        ok = np.abs(res) < tol
        new_t, new_c = tan_k.copy(), c_k.copy()
        own = np.zeros(tan_k.size, dtype=bool)
        members = []
        for k in range(tan_k.size):
            sel = ok & (beam == k)
            members.append(sel)
            if sel.sum() >= 3 and np.ptp(x[sel]) >= _MIN_PARALLAX_SPAN:
                new_t[k], new_c[k] = _line_fit(x[sel], t[sel], c_k[k])
                own[k] = True
        for k in range(tan_k.size):
            if own[k]:
                continue
            near = np.nonzero(own)[0]
            if near.size:
                near = near[np.argsort(np.abs(near - k), kind="stable")[:4]]
                new_c[k] = np.median(new_c[near])
            if members[k].any():
                new_t[k] = np.median(t[members[k]] - new_c[k] * x[members[k]])
        done = np.allclose(new_t, tan_k, atol=1e-12, rtol=0) and np.allclose(new_c, c_k, atol=1e-9)
        tan_k, c_k = new_t, new_c
        if done:
            break
    order = np.argsort(tan_k, kind="stable")
    return np.arctan(tan_k[order]), c_k[order]


def _on_beam_share(d, phi, incl, offsets) -> float:
    c = np.zeros_like(incl) if offsets is None else offsets
    beam, res = _assign(d, phi, np.tan(incl), c)
    return float(np.mean(np.abs(res) <= ON_BEAM_FRACTION * _local_spacing(incl)[beam]))


def fit_beam_table(
    points_xyz: np.ndarray,
    num_beams: int = 64,
    origin: Sequence[float] = (0.0, 0.0, 0.0),
    offsets: str = "auto",
    init: str = "data",
) -> BeamFit:
    """Fit ``num_beams`` beam elevations (and laser heights) from ``(N, 3+)`` points in the
    vehicle frame seen from ``origin`` (module docstring)."""
    if offsets not in ("auto", "on", "off"):
        raise ValueError(f"offsets must be 'auto', 'on' or 'off', got {offsets!r}")
    if num_beams < 2:
        raise ValueError(f"num_beams must be >= 2, got {num_beams}")
    d, phi = _geometry(points_xyz, origin)
    if d.size < num_beams:
        raise ValueError(
            f"the fit needs at least {num_beams} points at >= {_MIN_HORIZ_M} m from the sensor "
            f"axis, got {d.size}"
        )
    incl, empty = _single_origin(phi, num_beams, init)
    incl = _strict(incl)
    if offsets == "off" or init == "default_table":
        return BeamFit(incl, None, empty)
    q_lo, q_hi = np.quantile(np.tan(phi), [0.001, 0.999])
    tan0, c0 = _hough_start(d, phi, num_beams, 0.25 * (q_hi - q_lo) / (num_beams - 1))
    if tan0.size < num_beams:  # lasers without returns: between the others, median offset
        tan0 = np.tan(_fill(np.arctan(tan0), num_beams))
        c0 = np.full(num_beams, float(np.median(c0)) if c0.size else 0.0)
    incl_o, c_o = _refine_offsets(d, phi, tan0, c0)
    incl_o = _strict(incl_o)
    if offsets == "on":
        return BeamFit(incl_o, c_o, empty)
    gain = _on_beam_share(d, phi, incl_o, c_o) - _on_beam_share(d, phi, incl, None)
    return BeamFit(incl_o, c_o, empty) if gain >= _AUTO_GAIN else BeamFit(incl, None, empty)


def _strict(incl: np.ndarray) -> np.ndarray:
    """Sorted, with coincident beams (two starts on one laser) nudged 1e-9 rad apart."""
    incl = np.sort(np.asarray(incl, dtype=np.float64))
    for i in range(1, incl.size):
        if incl[i] <= incl[i - 1]:
            incl[i] = incl[i - 1] + 1e-9
    return incl


@dataclass
class FitReport:
    """How well a beam table explains a scan (:func:`fit_report`)."""

    num_points: int
    on_beam_share: float  #: points within ON_BEAM_FRACTION of the local spacing of their beam
    in_fov_share: float
    beam_count: np.ndarray  #: (B,) points per beam
    beam_residual_deg: np.ndarray  #: (B,) median |elevation residual| per beam (nan: no points)
    beam_on_share: np.ndarray  #: (B,) on-beam share per beam (nan: no points)
    warnings: list[str] = field(default_factory=list)

    def format(self, incl_deg: np.ndarray, offsets: np.ndarray | None) -> str:
        """The report as ``#``-comment lines (the printed table stays pasteable YAML)."""
        lines = [
            f"# fit report: {self.num_points} points; {100 * self.on_beam_share:.1f}% within "
            f"{ON_BEAM_FRACTION:g} of the local spacing of their beam (a right table: ~100% on "
            f"clean data; a table unrelated to the lasers: ~{200 * ON_BEAM_FRACTION:.0f}%); "
            f"{100 * self.in_fov_share:.1f}% inside the fan",
            "# beam  elev_deg  offset_m  points  median|res|_deg  on_beam",
        ]
        for k in range(incl_deg.size):
            off = 0.0 if offsets is None else float(offsets[k])
            lines.append(
                f"# {k:4d} {incl_deg[k]:9.4f} {off:9.3f} {int(self.beam_count[k]):7d} "
                f"{self.beam_residual_deg[k]:16.4f} {self.beam_on_share[k]:8.2f}"
            )
        lines += [f"# WARNING: {w}" for w in self.warnings]
        return "\n".join(lines)


def fit_report(lidar, points_xyz: np.ndarray) -> FitReport:
    """Residuals of ``points_xyz`` (vehicle frame) against ``lidar``'s beams and the warnings
    of a table that cannot be right (origin wrong, or not a spinning sensor seen from it)."""
    d, phi = _geometry(points_xyz, lidar.origin_xyz)
    incl = lidar.inclinations.numpy()
    offsets = None if lidar.offsets is None else lidar.offsets.numpy()
    c = np.zeros_like(incl) if offsets is None else offsets
    beam, res = _assign(d, phi, np.tan(incl), c)
    fov = lidar.in_fov(torch.from_numpy(phi), torch.from_numpy(d)).numpy()
    on = np.abs(res) <= ON_BEAM_FRACTION * _local_spacing(incl)[beam]
    count = np.bincount(beam, minlength=incl.size)
    resid = np.full(incl.size, np.nan)
    share = np.full(incl.size, np.nan)
    for k in np.nonzero(count)[0]:
        resid[k] = math.degrees(float(np.median(np.abs(res[beam == k]))))
        share[k] = float(on[beam == k].mean())
    report = FitReport(int(d.size), float(on.mean()), float(fov.mean()), count, resid, share)
    lo, hi = math.degrees(incl[0]), math.degrees(incl[-1])
    if lo < KNOWN_FAN_DEG[0] - _FAN_MARGIN_DEG or hi > KNOWN_FAN_DEG[1] + _FAN_MARGIN_DEG:
        report.warnings.append(
            f"the table spans {lo:.1f} to {hi:.1f} deg, more than {_FAN_MARGIN_DEG:g} deg beyond "
            f"every known spinning sensor ({KNOWN_FAN_DEG[0]} to {KNOWN_FAN_DEG[1]} deg): the "
            f"origin {lidar.origin_xyz} is probably not the sensor's; pass --origin X Y Z"
        )
    if report.on_beam_share < _MIN_ON_BEAM_SHARE:
        report.warnings.append(
            f"only {100 * report.on_beam_share:.1f}% of the points lie near a beam (a right "
            f"table puts ~100% there): the origin {lidar.origin_xyz} is probably not the "
            f"sensor's, or the points are not one spinning sensor's; pass --origin X Y Z"
        )
    if offsets is not None and abs(float(np.median(offsets))) > _MAX_MEDIAN_OFFSET_M:
        report.warnings.append(
            f"the lasers fit {float(np.median(offsets)):+.2f} m above the origin (median): real "
            f"lasers sit within {_MAX_MEDIAN_OFFSET_M} m of their sensor's origin, so the origin "
            f"height is probably off by that much; pass --origin X Y Z"
        )
    return report


def estimate_azimuth_bins(frames_xyz: Sequence[np.ndarray], lidar) -> tuple[int, float]:
    """Firings per turn from the azimuth gaps between neighbouring returns of one beam in one
    frame: the firing step is the typical gap, refined over gaps that are a few whole steps.

    Returns:
        ``(M, share)``: firings per turn, and the share of gaps within a quarter step of a
        whole number of steps (near 1 when the estimate explains the scan).
    """
    gaps = []
    for pts in frames_xyz:
        xyz = torch.as_tensor(np.asarray(pts, dtype=np.float64)[:, :3])
        if xyz.shape[0] == 0:
            continue
        az, el, rng = lidar.spherical(xyz)
        horiz = rng * torch.cos(el)
        beam = lidar.beam_index(el, horiz if lidar.offsets is not None else None).numpy()
        az = az.numpy()
        order = np.lexsort((az, beam))
        same = beam[order][1:] == beam[order][:-1]
        g = np.diff(az[order])[same]
        gaps.append(g[g > 1e-7])
    gap = np.concatenate(gaps) if gaps else np.zeros(0)
    if gap.size < 10:
        raise ValueError(f"too few returns to estimate the azimuth bins ({gap.size} gaps)")
    step = float(np.quantile(gap, 0.25))
    for _ in range(3):
        k = np.round(gap / step)
        whole = (k >= 1) & (k <= 4) & (np.abs(gap / step - k) < 0.25)
        step = float(gap[whole].sum() / k[whole].sum())
    k = np.round(gap / step)
    share = float(np.mean((k >= 1) & (np.abs(gap / step - k) < 0.25)))
    return int(round(2 * math.pi / step)), share
