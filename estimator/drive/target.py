"""What every valve is driven to: the target stroke and opening instant, and the drive's limits.

The default target is the **common reachable** one: the plateau stroke and opening instant that every
part within tolerance reaches within the drive's limits anywhere in the operating range (N_u over the
model's range, L_h and the preload force over ``operating_lh_um`` and ``operating_preload_n``). The
stroke falls with N_u, L_h and the preload force and rises with the scale, so the range is bounded by
two of its corners: the least stroke the largest scale gives (a warm part with a long idle stroke at
full load) and the most stroke the smallest scale gives (a cold part with no idle stroke at idle). The
target is the middle of that interval, shrunk at both ends by ``part_margin`` for the parts' own
structural spread; the opening instant is the middle of the instants those corners give at that
stroke, so every part needs an offset well inside the limits. A target that depends on the rail
pressure or the temperature would let two injectors of one engine at different operating points
differ; this one does not.

``default = "nominal"`` keeps the earlier rule: the nominal injector's stroke and opening instant
under the standard drive at ``nominal_preload_n`` (which a warm part with a long idle stroke cannot
reach at full load). A configured ``stroke_um`` or ``opening_us`` is used as given.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

from estimator.drive.response import respond
from estimator.drive.standard import SHAPE_TOLERANCE, AmplifierDrive
from estimator.model.fast_sim import FastSimulator
from estimator.model.parameters import NOMINAL_PRELOAD_N

NOMINAL_NU_N_PER_V = 16.4      # Table 3's N_u at room temperature (the nominal injector of default = "nominal")
NOMINAL_LH_UM = 3.0            # and its idle stroke
DEFAULT_RULES = ("reachable", "nominal")
AMPLIFIER_DRIVES = ("learned", "trapezoid")   # besides the path of a current table
# the preload forces (N) of a correction's table: dense near idle, where the opening instant bends
PRELOAD_TABLE_N = (28.0, 31.0, 34.0, 37.0, 40.0, 44.0, 48.0, 55.0, 65.0, 80.0, 100.0, 130.0, 170.0, 220.0, 300.0)
MAX_TABLE_ROWS = 16


def _pair(name: str, value: tuple[float, float], lo_min: float = -math.inf) -> None:
    lo, hi = value
    if not (math.isfinite(lo) and math.isfinite(hi) and lo_min <= lo < hi):
        raise ValueError(f"{name} = {value}: need {lo_min:g} <= low < high" if math.isfinite(lo_min)
                         else f"{name} = {value}: need low < high")


@dataclass(frozen=True)
class DriveTarget:
    """What every valve should do, and how the drive may be changed to make it.

    ``stroke_um`` (plateau stroke, µm) and ``opening_us`` (opening instant after the standard drive's
    start of charging, µs): None takes the ``default`` rule's (see the module). ``scale_limits``: the
    plateau current relative to the amplifier's standard drive; ``offset_limits_us``: the start of
    charging relative to it. ``amplifier_drive``: the amplifier's standard drive, ``learned`` from each
    injector's first injections, ``trapezoid`` (the built-in one) or the path of a current table
    (CSV t_s,current_A); ``drive_tolerance``: the relative RMS of a measured current its scaled standard
    drive may leave unexplained before the correction is held; ``learn_injections``: how many injections
    at the standard drive a learned drive averages.
    """

    stroke_um: float | None = None
    opening_us: float | None = None
    default: str = "reachable"
    scale_limits: tuple[float, float] = (0.5, 1.5)
    offset_limits_us: tuple[float, float] = (-50.0, 50.0)
    operating_lh_um: tuple[float, float] = (0.0, 10.0)
    operating_preload_n: tuple[float, float] = (NOMINAL_PRELOAD_N, 300.0)
    part_margin: float = 0.08
    nominal_nu_n_per_v: float = NOMINAL_NU_N_PER_V
    nominal_lh_um: float = NOMINAL_LH_UM
    nominal_preload_n: float = NOMINAL_PRELOAD_N
    amplifier_drive: str = "learned"
    drive_tolerance: float = SHAPE_TOLERANCE
    learn_injections: int = 4
    table_preloads_n: tuple[float, ...] = PRELOAD_TABLE_N

    def __post_init__(self) -> None:
        _pair("scale_limits", self.scale_limits, 0.0)
        if self.scale_limits[0] <= 0:
            raise ValueError(f"scale_limits = {self.scale_limits}: need 0 < low < high")
        _pair("offset_limits_us", self.offset_limits_us)
        _pair("operating_lh_um", self.operating_lh_um, 0.0)
        _pair("operating_preload_n", self.operating_preload_n, 0.0)
        for name in ("stroke_um", "opening_us"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} = {v}: must be positive (or unset for the default rule's)")
        if self.default not in DEFAULT_RULES:
            raise ValueError(f"default = {self.default!r}: must be one of {', '.join(DEFAULT_RULES)}")
        if not (0.0 <= self.part_margin < 0.5):
            raise ValueError(f"part_margin = {self.part_margin}: must be in [0, 0.5)")
        if not (0.0 < self.drive_tolerance <= 1.0):
            raise ValueError(f"drive_tolerance = {self.drive_tolerance}: must be in (0, 1]")
        if not (1 <= self.learn_injections <= 100):
            raise ValueError(f"learn_injections = {self.learn_injections}: must be 1..100")
        rows = self.table_preloads_n
        if not (2 <= len(rows) <= MAX_TABLE_ROWS and all(math.isfinite(f) and f >= 0 for f in rows)
                and all(b > a for a, b in itertools.pairwise(rows))):
            raise ValueError(f"table_preloads_n = {rows}: 2..{MAX_TABLE_ROWS} increasing preload forces (N) >= 0")
        if not self.amplifier_drive:
            raise ValueError("amplifier_drive: 'learned', 'trapezoid' or the path of a current table")

    @property
    def drive_file(self) -> str | None:
        """The current table's path, when the amplifier's drive is given as one."""
        return None if self.amplifier_drive in AMPLIFIER_DRIVES else self.amplifier_drive


def _corners(sim: FastSimulator, t: DriveTarget) -> list[tuple[float, float, float]]:
    """(N_u N/V, L_h µm, preload N) at the corners of the operating range."""
    return [(nu, lh, f) for nu in sim.nu_range for lh in t.operating_lh_um for f in t.operating_preload_n]


def reachable_stroke(sim: FastSimulator, t: DriveTarget, drive: AmplifierDrive | None = None) -> tuple[float, float]:
    """(low, high) plateau stroke (µm) every part within tolerance reaches within the scale limits over
    the operating range, shrunk by ``part_margin``; ValueError when the limits leave none."""
    lo_s, hi_s = t.scale_limits
    corners = _corners(sim, t)
    most = [respond(sim, hi_s, *c, drive)[0] for c in corners]
    if not all(math.isfinite(s) for s in most):
        raise ValueError(f"a valve of the operating range does not open at the largest scale {hi_s:g}")
    least = [s for s in (respond(sim, lo_s, *c, drive)[0] for c in corners) if math.isfinite(s)]
    lo = (max(least) if least else 0.0) * (1 + t.part_margin)
    hi = min(most) * (1 - t.part_margin)
    if not lo < hi:
        raise ValueError(f"no plateau stroke is reached by every part with scale_limits = {t.scale_limits}: "
                         f"the smallest scale gives up to {lo:.2f} µm and the largest at least {hi:.2f} µm "
                         f"(with part_margin {t.part_margin:g}); widen scale_limits or set stroke_um")
    return lo, hi


def scale_for_stroke(sim: FastSimulator, stroke_um: float, nu: float, lh_um: float, f_open_n: float,
                     limits: tuple[float, float], drive: AmplifierDrive | None = None) -> tuple[float, float, float]:
    """(scale, stroke µm, opening µs) that gives ``stroke_um`` at one operating point within ``limits``
    (secant steps on the stroke, which is close to linear in the scale)."""
    lo, hi = limits
    a, sa = lo, respond(sim, lo, nu, lh_um, f_open_n, drive)
    b, sb = hi, respond(sim, hi, nu, lh_um, f_open_n, drive)
    if not math.isfinite(sa[0]):
        sa = (0.0, math.nan)
    s, got = b, sb
    for _ in range(4):
        if sb[0] == sa[0]:
            break
        s = min(max(a + (stroke_um - sa[0]) * (b - a) / (sb[0] - sa[0]), lo), hi)
        got = respond(sim, s, nu, lh_um, f_open_n, drive)
        if not math.isfinite(got[0]) or abs(got[0] - stroke_um) < 1e-3:
            break
        a, sa = b, sb
        b, sb = s, got
    return s, got[0], got[1]


def resolve(sim: FastSimulator, t: DriveTarget, drive: AmplifierDrive | None = None) -> tuple[float, float]:
    """(stroke µm, opening µs) the target asks for with ``sim`` (the configured parameters) and the
    amplifier's standard drive; ValueError when the default rule finds none."""
    if t.stroke_um is not None and t.opening_us is not None:
        return t.stroke_um, t.opening_us
    if t.default == "nominal":
        got = respond(sim, 1.0, t.nominal_nu_n_per_v, t.nominal_lh_um, t.nominal_preload_n, drive)
        if not (math.isfinite(got[0]) and math.isfinite(got[1])):
            raise ValueError("the nominal injector's valve does not open under the standard drive")
        return (t.stroke_um if t.stroke_um is not None else got[0],
                t.opening_us if t.opening_us is not None else got[1])
    if t.stroke_um is not None:
        stroke = t.stroke_um
    else:
        lo, hi = reachable_stroke(sim, t, drive)
        stroke = 0.5 * (lo + hi)
    if t.opening_us is not None:
        return stroke, t.opening_us
    openings = [scale_for_stroke(sim, stroke, *c, t.scale_limits, drive)[2] for c in _corners(sim, t)]
    openings = [o for o in openings if math.isfinite(o)]
    if not openings:
        raise ValueError(f"no valve of the operating range opens with a stroke of {stroke:.2f} µm")
    o_lo, o_hi = min(openings), max(openings)
    lo_off, hi_off = t.offset_limits_us
    if o_hi - o_lo > (hi_off - lo_off) * (1 - 2 * t.part_margin):
        raise ValueError(f"the opening instants of the operating range span {o_hi - o_lo:.1f} µs at "
                         f"{stroke:.2f} µm, more than offset_limits_us = {t.offset_limits_us} allow; widen them "
                         "or set opening_us")
    return stroke, 0.5 * (o_lo + o_hi) + 0.5 * (lo_off + hi_off)
