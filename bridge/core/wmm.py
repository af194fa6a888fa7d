"""The Earth's main field from the World Magnetic Model (via pygeomag).

pygeomag is a small, maintained, pure-Python WMM implementation that ships
the official coefficient files (WMM2025, valid to 2030), so no data is fetched
at run time. We wrap it so the rest of the package speaks gauss and NED.
"""

from __future__ import annotations

import datetime as _dt
import functools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from pygeomag import GeoMag

NT_PER_GAUSS = 1e5


@dataclass(frozen=True, slots=True)
class EarthField:
    """Main-field vector at one place and time.

    ``north_G``/``east_G``/``down_G`` are the NED components in gauss;
    ``declination_deg`` is positive east (true = magnetic + declination),
    ``inclination_deg`` (dip) positive down.
    """

    north_G: float
    east_G: float
    down_G: float
    declination_deg: float
    inclination_deg: float

    @property
    def ned_G(self) -> npt.NDArray[np.float64]:
        """Field vector (N, E, D) in gauss."""
        return np.array([self.north_G, self.east_G, self.down_G])

    @property
    def total_G(self) -> float:
        """Total intensity |B| in gauss."""
        return math.sqrt(self.north_G**2 + self.east_G**2 + self.down_G**2)

    @property
    def horizontal_G(self) -> float:
        """Horizontal intensity in gauss."""
        return math.hypot(self.north_G, self.east_G)


def decimal_year(when: _dt.date | _dt.datetime | float | None = None) -> float:
    """Decimal year of ``when`` (default: today, UTC); floats pass through."""
    if when is None:
        when = _dt.datetime.now(_dt.UTC)
    if isinstance(when, float | int):
        return float(when)
    if isinstance(when, _dt.datetime):
        when = when.date()
    start = _dt.date(when.year, 1, 1)
    days = (_dt.date(when.year + 1, 1, 1) - start).days
    return when.year + (when - start).days / days


@functools.lru_cache(maxsize=1)
def _model() -> GeoMag:
    return GeoMag()


@functools.lru_cache(maxsize=256)
def _field_cached(lat: float, lon: float, alt_m: float, year: float) -> EarthField:
    r = _model().calculate(
        glat=lat, glon=lon, alt=alt_m / 1000.0, time=year, allow_date_outside_lifespan=True
    )
    return EarthField(
        north_G=float(r.x) / NT_PER_GAUSS,
        east_G=float(r.y) / NT_PER_GAUSS,
        down_G=float(r.z) / NT_PER_GAUSS,
        declination_deg=float(r.d),
        inclination_deg=float(r.i),
    )


def earth_field(
    latitude_deg: float,
    longitude_deg: float,
    altitude_m: float = 0.0,
    when: _dt.date | _dt.datetime | float | None = None,
) -> EarthField:
    """WMM main field at a WGS-84 position (altitude above the ellipsoid, metres).

    Raises ``ValueError`` for a latitude outside [-90, 90] or a non-finite input.
    Results are cached on a rounded position (0.01 deg, 10 m, 0.01 year): the
    field changes far less than sensor noise over such steps.
    """
    for name, v in (
        ("latitude", latitude_deg),
        ("longitude", longitude_deg),
        ("altitude", altitude_m),
    ):
        if not math.isfinite(v):
            raise ValueError(f"{name} must be finite, got {v!r}")
    if not -90.0 <= latitude_deg <= 90.0:
        raise ValueError(f"latitude {latitude_deg} outside [-90, 90]")
    lon = ((longitude_deg + 180.0) % 360.0) - 180.0
    return _field_cached(
        round(latitude_deg, 2), round(lon, 2), round(altitude_m, -1), round(decimal_year(when), 2)
    )
