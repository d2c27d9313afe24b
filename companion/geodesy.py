"""Geodesy for the fleet frame: WGS-84 latitude/longitude/altitude <-> local NED about an origin.

Pure (numpy only). The fleet frame (`[fleet] origin = [lat_deg, lon_deg, alt_m]`) is the local
tangent plane at that point: north, east, down along the WGS-84 ellipsoid's normal there, in
metres, through Earth-centred Earth-fixed (ECEF) coordinates, so it is exact at any distance
(no flat-earth approximation in the conversion itself).

Each autopilot's local NED frame is taken as the tangent plane at its own origin (the EKF
origin, GPS_GLOBAL_ORIGIN). Between two tangent planes the map is rigid: a rotation (the two
normals differ by the angle between the points seen from the Earth's centre, ~d / 6371 km: 0.009
degrees per km, and north turns as the meridians converge, up to as much again) and a translation. `Placement` is that map, exact between the two tangent planes.
What it does not model is each autopilot's own projection of GPS into its local frame (PX4:
azimuthal equidistant on a 6371 km sphere; ArduPilot: equirectangular on 6378.1 km, with altitude
for down), which departs from its tangent plane by second-order terms (down: d^2 / (2 R), 8 cm
at 1 km from the vehicle's own origin) and a scale of up to ~0.3 % (the sphere against the
ellipsoid): docs/fleet.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

WGS84_A = 6378137.0  # semi-major axis (m)
WGS84_F = 1.0 / 298.257223563  # flattening
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)  # first eccentricity squared


def check_lla(lla: Any, what: str = "position") -> tuple[float, float, float]:
    """(lat_deg, lon_deg, alt_m) as floats; ValueError when it is not a geodetic point."""
    try:
        lat, lon, alt = (float(v) for v in lla)
    except (TypeError, ValueError):
        raise ValueError(f"{what}: expected [lat_deg, lon_deg, alt_m], got {lla!r}") from None
    if not all(math.isfinite(v) for v in (lat, lon, alt)):
        raise ValueError(f"{what}: not finite: {lla!r}")
    if not -90.0 <= lat <= 90.0:
        raise ValueError(f"{what}: latitude {lat} outside [-90, 90] degrees")
    if not -180.0 <= lon <= 180.0:
        raise ValueError(f"{what}: longitude {lon} outside [-180, 180] degrees")
    if not -12000.0 <= alt <= 100000.0:
        raise ValueError(f"{what}: altitude {alt} m outside [-12000, 100000]")
    return lat, lon, alt


def lla_to_ecef(lla: Any) -> FloatArray:
    """ECEF (m) of a WGS-84 (lat_deg, lon_deg, alt_m above the ellipsoid)."""
    lat, lon, alt = (math.radians(float(lla[0])), math.radians(float(lla[1])), float(lla[2]))
    s, c = math.sin(lat), math.cos(lat)
    n = WGS84_A / math.sqrt(1.0 - WGS84_E2 * s * s)  # prime vertical radius of curvature
    return np.array([(n + alt) * c * math.cos(lon), (n + alt) * c * math.sin(lon), (n * (1.0 - WGS84_E2) + alt) * s])


def ecef_to_lla(xyz: Any) -> tuple[float, float, float]:
    """(lat_deg, lon_deg, alt_m) of an ECEF point (iterated to well below a micrometre)."""
    x, y, z = (float(v) for v in xyz)
    lon = math.atan2(y, x)
    p = math.hypot(x, y)
    lat = math.atan2(z, p * (1.0 - WGS84_E2))
    alt = 0.0
    for _ in range(10):
        s = math.sin(lat)
        n = WGS84_A / math.sqrt(1.0 - WGS84_E2 * s * s)
        alt = p / math.cos(lat) - n if abs(lat) < math.radians(80.0) else z / s - n * (1.0 - WGS84_E2)
        new = math.atan2(z, p * (1.0 - WGS84_E2 * n / (n + alt)))
        if abs(new - lat) < 1e-14:
            lat = new
            break
        lat = new
    s = math.sin(lat)
    n = WGS84_A / math.sqrt(1.0 - WGS84_E2 * s * s)
    alt = p / math.cos(lat) - n if abs(lat) < math.radians(80.0) else z / s - n * (1.0 - WGS84_E2)
    return math.degrees(lat), math.degrees(lon), alt


def ecef_to_ned_rotation(lat_deg: float, lon_deg: float) -> FloatArray:
    """The rotation taking ECEF vectors to NED at (lat, lon): rows are north, east, down."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
    return np.array([[-sl * co, -sl * so, cl],
                     [-so, co, 0.0],
                     [-cl * co, -cl * so, -sl]])


def lla_to_ned(lla: Any, origin: Any) -> FloatArray:
    """NED (m) of a geodetic point in the tangent plane at the geodetic `origin`."""
    out: FloatArray = ecef_to_ned_rotation(float(origin[0]), float(origin[1])) @ (lla_to_ecef(lla) - lla_to_ecef(origin))
    return out


def ned_to_lla(ned: Any, origin: Any) -> tuple[float, float, float]:
    """The geodetic point at NED (m) in the tangent plane at `origin`."""
    r = ecef_to_ned_rotation(float(origin[0]), float(origin[1]))
    return ecef_to_lla(lla_to_ecef(origin) + r.T @ np.asarray(ned, dtype=float))


@dataclass(frozen=True)
class Placement:
    """Where a local NED frame sits in the fleet frame: fleet = rotation @ local + offset.

    `offset` is the local frame's origin in the fleet frame (NED, m); `rotation` turns local
    axes into fleet axes (identity for a configured offset, within ~1e-4 of it for tangent
    planes a few km apart)."""

    offset: FloatArray
    rotation: FloatArray = field(default_factory=lambda: np.eye(3))
    source: str = "offset_ned"

    def to_fleet(self, points: Any) -> FloatArray:
        """Local NED points (..., 3) in the fleet frame."""
        out: FloatArray = np.asarray(points, dtype=float) @ self.rotation.T + self.offset
        return out

    def to_local(self, points: Any) -> FloatArray:
        """Fleet-frame points (..., 3) in the local NED frame."""
        out: FloatArray = (np.asarray(points, dtype=float) - self.offset) @ self.rotation
        return out

    def vectors_to_local(self, vectors: Any) -> FloatArray:
        """Fleet-frame vectors (velocities, accelerations: no offset) in the local frame."""
        out: FloatArray = np.asarray(vectors, dtype=float) @ self.rotation
        return out

    def halfspaces_to_local(self, A: Any, b: Any) -> tuple[FloatArray, FloatArray]:
        """Rows of A q <= b over fleet points q, as rows over local points p (q = R p + t):
        (A R) p <= b - A t."""
        a = np.asarray(A, dtype=float)
        return a @ self.rotation, np.asarray(b, dtype=float) - a @ self.offset

    def box_to_local(self, lo: Any, hi: Any) -> tuple[FloatArray, FloatArray]:
        """The smallest local axis-aligned box holding a fleet-frame box (its 8 corners)."""
        lo_a, hi_a = np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)
        corners = np.array([[(lo_a, hi_a)[i][0], (lo_a, hi_a)[j][1], (lo_a, hi_a)[k][2]]
                            for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        local = self.to_local(corners)
        return local.min(axis=0), local.max(axis=0)

    def angle_deg(self) -> float:
        """How far the local axes are turned from the fleet's (degrees)."""
        c = (float(np.trace(self.rotation)) - 1.0) / 2.0
        return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def placement(local_origin: Any, fleet_origin: Any, source: str = "gps_global_origin") -> Placement:
    """The placement of the tangent plane at the geodetic `local_origin` (an autopilot's EKF
    origin) in the tangent plane at `fleet_origin`."""
    lat_l, lon_l = float(local_origin[0]), float(local_origin[1])
    lat_f, lon_f = float(fleet_origin[0]), float(fleet_origin[1])
    # local NED -> ECEF -> fleet NED
    rotation = ecef_to_ned_rotation(lat_f, lon_f) @ ecef_to_ned_rotation(lat_l, lon_l).T
    return Placement(lla_to_ned(local_origin, fleet_origin), rotation, source)


def local_origin_from_home(home_lla: Any, home_local: Any) -> tuple[float, float, float]:
    """The geodetic local origin of a frame in which the geodetic point `home_lla` (HOME_POSITION's
    latitude, longitude, altitude) sits at local NED `home_local` (its x, y, z)."""
    return ned_to_lla(-np.asarray(home_local, dtype=float), home_lla)
