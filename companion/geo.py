"""Frames of reference, all through pyproj: WGS84, UTM (one zone per flight) and local NED.

Nothing else in the project does trigonometry on latitudes. Functions are named `<from>_to_<to>`,
angles in degrees where they are geodetic (as MAVLink and pyproj give them), lengths in metres,
altitudes ellipsoidal unless named `_amsl`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pyproj import CRS, Transformer
from pyproj.enums import TransformDirection

from companion.errors import InputError

FloatArray = NDArray[np.float64]

__all__ = ["LocalNed", "Utm", "utm_zone_for"]


def _check_geodetic(lat_deg: float, lon_deg: float) -> None:
    """InputError unless a finite latitude in [-90, 90] and longitude in [-180, 180] degrees."""
    if not (np.isfinite(lat_deg) and -90.0 <= lat_deg <= 90.0):
        raise InputError(f"latitude must be in [-90, 90] degrees, got {lat_deg!r}")
    if not (np.isfinite(lon_deg) and -180.0 <= lon_deg <= 180.0):
        raise InputError(f"longitude must be in [-180, 180] degrees, got {lon_deg!r}")


@dataclass(frozen=True)
class LocalNed:
    """The local tangent plane (north, east, down) at a geodetic origin on the WGS84 ellipsoid.

    The same frame PX4 and ArduPilot report LOCAL_POSITION_NED in, about their own origins.
    """

    lat_deg: float
    lon_deg: float
    alt_m: float
    _enu: Transformer = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        _check_geodetic(self.lat_deg, self.lon_deg)
        pipeline = (
            "+proj=pipeline +step +proj=axisswap +order=2,1 +step +proj=unitconvert "
            "+xy_in=deg +xy_out=rad +step +proj=cart +ellps=WGS84 "
            f"+step +proj=topocentric +ellps=WGS84 +lat_0={self.lat_deg!r} "
            f"+lon_0={self.lon_deg!r} +h_0={self.alt_m!r}"
        )
        object.__setattr__(self, "_enu", Transformer.from_pipeline(pipeline))

    def geodetic_to_ned(
        self, lat_deg: ArrayLike, lon_deg: ArrayLike, alt_m: ArrayLike
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(north_m, east_m, down_m) of WGS84 points (arguments broadcast together)."""
        lat, lon, alt = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64)
                                              for a in (lat_deg, lon_deg, alt_m)))
        east, north, up = self._enu.transform(lat, lon, alt)
        return np.asarray(north), np.asarray(east), -np.asarray(up)

    def ned_to_geodetic(
        self, north_m: ArrayLike, east_m: ArrayLike, down_m: ArrayLike
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(lat_deg, lon_deg, alt_m) of points in this frame (arguments broadcast together)."""
        north, east, down = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64)
                                                  for a in (north_m, east_m, down_m)))
        lat, lon, alt = self._enu.transform(east, north, -down,
                                            direction=TransformDirection.INVERSE)
        return np.asarray(lat), np.asarray(lon), np.asarray(alt)


def utm_zone_for(lat_deg: float, lon_deg: float) -> int:
    """The EPSG code of the WGS84 / UTM zone that contains a point (326xx north, 327xx south)."""
    _check_geodetic(lat_deg, lon_deg)
    zone = int((lon_deg + 180.0) // 6.0) % 60 + 1
    return (32600 if lat_deg >= 0.0 else 32700) + zone


@dataclass(frozen=True)
class Utm:
    """One UTM zone for a whole flight: easting and northing in metres (EPSG 326xx / 327xx)."""

    epsg: int
    _forward: Transformer = field(init=False, repr=False, compare=False)
    _inverse: Transformer = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not (32601 <= self.epsg <= 32660 or 32701 <= self.epsg <= 32760):
            reason = f"must be a WGS84 / UTM zone (326xx, 327xx), got {self.epsg!r}"
            raise InputError(f"the EPSG code {reason}", reason=reason)
        crs = CRS.from_epsg(self.epsg)
        object.__setattr__(
            self, "_forward", Transformer.from_crs("EPSG:4326", crs, always_xy=True)
        )
        object.__setattr__(
            self, "_inverse", Transformer.from_crs(crs, "EPSG:4326", always_xy=True)
        )

    @staticmethod
    def at(lat_deg: float, lon_deg: float) -> Utm:
        """The zone that contains a point (the search area's centre, say)."""
        return Utm(utm_zone_for(lat_deg, lon_deg))

    def geodetic_to_utm(
        self, lat_deg: ArrayLike, lon_deg: ArrayLike
    ) -> tuple[FloatArray, FloatArray]:
        """(easting_m, northing_m) of WGS84 points."""
        easting, northing = self._forward.transform(
            np.asarray(lon_deg, dtype=np.float64), np.asarray(lat_deg, dtype=np.float64)
        )
        return np.asarray(easting), np.asarray(northing)

    def utm_to_geodetic(
        self, easting_m: ArrayLike, northing_m: ArrayLike
    ) -> tuple[FloatArray, FloatArray]:
        """(lat_deg, lon_deg) of points in this zone."""
        lon, lat = self._inverse.transform(
            np.asarray(easting_m, dtype=np.float64), np.asarray(northing_m, dtype=np.float64)
        )
        return np.asarray(lat), np.asarray(lon)
