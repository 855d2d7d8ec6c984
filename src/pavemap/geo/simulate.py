"""Simulated GPS of a drive with a known geo origin (tests and ``bench/geo_bench.py``).

Noise model, per horizontal axis (east, north), in metres:
- ``white``: independent N(0, sigma^2) per fix (a good receiver's jitter);
- ``drift``: a first-order Gauss-Markov bias with stationary std ``sigma`` and correlation time
  ``tau_s`` (multipath and atmosphere: slow, the same for neighbouring fixes), plus a tenth of it white.
Outliers: a share of fixes moved by 20-80 m in a random direction (multipath jumps).
Altitude: the true altitude plus N(0, (2 sigma)^2) (GNSS heights are about twice as noisy).
"""

from __future__ import annotations

import numpy as np

from pavemap.geo.tangent import local_tangent
from pavemap.io.gps import GpsTrack, make_track
from pavemap.types import GeoOrigin, Sequence


def gauss_markov(n: int, dt: float, sigma: float, tau_s: float, rng: np.random.Generator) -> np.ndarray:
    """(n,) a stationary first-order Gauss-Markov series with std ``sigma``, correlation time ``tau_s``."""
    a = float(np.exp(-dt / tau_s))
    out = np.empty(n)
    out[0] = rng.normal(0.0, sigma)
    e = rng.normal(0.0, sigma * np.sqrt(1 - a * a), n)
    for k in range(1, n):
        out[k] = a * out[k - 1] + e[k]
    return out


def simulate_track(seq: Sequence, origin: GeoOrigin, *, hz: float = 1.0, sigma: float = 3.0,
                   noise: str = "white", outliers: float = 0.02, tau_s: float = 300.0, t0: float = 0.0,
                   seed: int = 0, source: str = "simulated", lever_arm: tuple[float, float, float] | None = None,
                   heading_sigma_deg: float | None = None) -> GpsTrack:
    """Fixes at ``hz`` over the drive's time span, times ``t0`` + frame time (``t0`` > 1e8: absolute).

    ``lever_arm``: the antenna's offset from the camera (x forward, y left, z up; the fixes are the
    antenna's); ``heading_sigma_deg``: the fixes carry the true course with that noise (else none)."""
    from pavemap.geo.georef import antenna_positions, travel_yaw

    rng = np.random.default_rng(seed)
    ft = np.array([f.timestamp for f in seq.frames], dtype=np.float64)
    traj = antenna_positions(seq.trajectory(), lever_arm)
    start = ft[0] + rng.uniform(0, 1.0 / hz)  # the receiver's clock is not the camera's
    t = np.arange(start, ft[-1], 1.0 / hz)
    xyz = np.stack([np.interp(t, ft, traj[:, k]) for k in range(3)], axis=1)
    lt = local_tangent(origin)
    e, n = lt.world_to_enu(xyz[:, 0], xyz[:, 1])
    if noise == "white":
        de, dn = rng.normal(0, sigma, len(t)), rng.normal(0, sigma, len(t))
    elif noise == "drift":
        de = gauss_markov(len(t), 1.0 / hz, sigma, tau_s, rng) + rng.normal(0, 0.1 * sigma, len(t))
        dn = gauss_markov(len(t), 1.0 / hz, sigma, tau_s, rng) + rng.normal(0, 0.1 * sigma, len(t))
    else:
        raise ValueError(f"noise must be white or drift, got {noise!r}")
    bad = rng.random(len(t)) < outliers
    ang = rng.uniform(0, 2 * np.pi, len(t))
    jump = rng.uniform(20.0, 80.0, len(t))
    de, dn = de + bad * jump * np.cos(ang), dn + bad * jump * np.sin(ang)
    x, y = lt.enu_to_world(e + de, n + dn)
    lon, lat = lt.to_lonlat(x, y)
    alt = origin.alt + xyz[:, 2] + rng.normal(0, 2 * sigma, len(t))
    heading: list = [None] * len(t)
    if heading_sigma_deg is not None:
        yaw = np.degrees(travel_yaw(xyz))  # the course over ground, world frame
        heading = list((origin.heading_deg - yaw + rng.normal(0, heading_sigma_deg, len(t))) % 360.0)
    rows = list(zip(t + t0, lat, lon, alt, heading, strict=True))
    return make_track(source, "simulated", rows, absolute=t0 > 1e8)


__all__ = ["gauss_markov", "simulate_track"]
