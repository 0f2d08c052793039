"""Gridding of a levelled anomaly flown along lines, and the survey's map products.

The last step of the survey path (DESIGN.md, Survey products): the levelled total-field
anomaly, sampled every metre or so along lines tens of metres apart, becomes a regular grid
(Fatiando a Terra's verde and harmonica), written as NetCDF and GeoTIFF in UTM, and drawn
as a map.

How the grid is made (:func:`grid_anomaly`):

1. The line spacing is measured from the positions alone (:func:`line_spacing`): the
   direction of the lines is the dominant direction between nearest neighbours, and the
   spacing is the median distance between the lines' centres across that direction.
2. The samples are reduced to the medians of square blocks a third of a line spacing wide
   (``verde.BlockReduce``). Along a line the samples are far denser than across lines, so
   the reduction loses nothing the lines can resolve, keeps the fit small (a few hundred
   points for a 300 m x 210 m survey) and takes the median against spikes.
3. A bi-harmonic spline (``verde.Spline``) or equivalent sources
   (``harmonica.EquivalentSources``, data and grid on one constant-height surface: the map
   is at the flight's height) is fitted to the block medians and evaluated on the grid.
   The default grid spacing is also a third of the line spacing, rounded to a round
   number.
4. Grid nodes farther than one line spacing from every sample are blanked
   (``verde.distance_mask``): inside the survey every node is within half a spacing of a
   line, so the survey keeps its edges while holes wider than two lines are not invented.

Coordinates: local metres ``north``, ``east`` from an origin (lat0, lon0), flat-earth as
everywhere in maglog (``north = (lat - lat0) * 111_320``,
``east = (lon - lon0) * 111_320 * cos(lat0)``). :func:`to_utm` resamples the grid onto a
regular UTM grid (pyproj; the zone from the origin), which the GeoTIFF needs.

Every function raises :class:`~maglog.calib.survey_errors.SurveyError` with a one-line
message on input it cannot use.
"""

from dataclasses import dataclass
from pathlib import Path
import importlib
import math

import numpy as np

from .survey_errors import SurveyError


__all__ = ["METHODS", "MIN_POINTS", "line_spacing", "grid_anomaly", "grid_summary",
           "utm_epsg", "to_utm", "write_netcdf", "read_netcdf", "write_geotiff", "map_plot",
           "Peak", "peak"]


#: The gridders :func:`grid_anomaly` knows.
METHODS = ("spline", "eqs")
#: The fewest finite samples :func:`grid_anomaly` grids.
MIN_POINTS = 20
#: Metres per degree of latitude (the flat-earth conversion used by the simulator).
METRES_PER_DEGREE = 111_320.0
#: Equivalent sources' damping when none is given (relative: verde and harmonica scale the
#: Jacobian's columns to unit variance before the ridge).
EQS_DEFAULT_DAMPING = 1e-3
#: Grids larger than this are refused (a spacing far too fine for the survey).
MAX_NODES = 4_000_000

_NORTHING, _EASTING = "northing", "easting"


# -- line spacing --------------------------------------------------------------------------

def _axial_mean(angles):
    """Mean of undirected angles (radians, modulo pi)."""
    return 0.5 * math.atan2(np.mean(np.sin(2 * angles)), np.mean(np.cos(2 * angles)))


def line_spacing(north, east):
    """The median distance (m) between adjacent survey lines, from the positions alone.

    The lines' direction is the dominant direction from each sample to its nearest
    neighbour (along a line samples are metres apart, lines tens of metres); the samples
    whose neighbour lies within 20 degrees of that direction (the lines, not the turns or
    tie lines) are projected across it and split where the projections jump by more than
    three along-line sample spacings. Clusters of fewer than a fifth of the median
    cluster's samples (a turn, a stray fix) are ignored. Returns ``(spacing_m,
    direction_deg, n_lines)``, the direction clockwise from north in [0, 180).

    Raises SurveyError when only one line is found.
    """
    from scipy.spatial import cKDTree

    points = np.column_stack([np.asarray(east, float), np.asarray(north, float)])
    points = np.unique(points, axis=0)
    if len(points) < 3:
        raise SurveyError(f"too few distinct positions to find survey lines: {len(points)}")
    distance, index = cKDTree(points).query(points, k=2)
    step = points[index[:, 1]] - points
    angle = np.arctan2(step[:, 1], step[:, 0])       # from east, anticlockwise
    # The mode of the doubled angle (undirected), refined by the axial mean around it.
    counts, edges = np.histogram(np.mod(2 * angle, 2 * np.pi), bins=72, range=(0, 2 * np.pi))
    mode = 0.5 * (edges[np.argmax(counts)] + np.pi / 72)
    along = np.abs(np.angle(np.exp(2j * (angle - mode)))) < 2 * np.radians(20)
    direction = _axial_mean(angle[along])
    along = np.abs(np.angle(np.exp(2j * (angle - direction)))) < 2 * np.radians(20)
    across = np.sort(-np.sin(direction) * points[along, 0] + np.cos(direction) * points[along, 1])
    jump = 3.0 * float(np.median(distance[along, 1]))
    splits = np.flatnonzero(np.diff(across) > jump) + 1
    clusters = np.split(across, splits)
    sizes = np.array([len(c) for c in clusters])
    centres = np.array([np.median(c) for c, s in zip(clusters, sizes)
                        if s >= max(5, 0.2 * np.median(sizes))])
    if len(centres) < 2:
        raise SurveyError("one survey line only: a map needs at least two")
    spacing = float(np.median(np.diff(np.sort(centres))))
    direction_deg = float(np.degrees(np.pi / 2 - direction) % 180.0)
    return spacing, direction_deg, len(centres)


# -- gridding ------------------------------------------------------------------------------

def _check_points(north, east, value):
    arrays = [np.asarray(a, dtype=float) for a in (north, east, value)]
    if any(a.ndim != 1 for a in arrays) or len({a.size for a in arrays}) != 1:
        shapes = ", ".join(str(a.shape) for a in arrays)
        raise SurveyError(f"north, east and value must be 1-D of one length, not {shapes}")
    north, east, value = arrays
    if value.size and not np.isfinite(value).any():
        raise SurveyError(f"every anomaly value is NaN: nothing to grid ({value.size} samples)")
    finite = np.isfinite(north) & np.isfinite(east) & np.isfinite(value)
    if finite.sum() < MIN_POINTS:
        raise SurveyError(f"too few points to grid: {int(finite.sum())} finite samples "
                          f"(at least {MIN_POINTS})")
    return north[finite], east[finite], value[finite]


def _positive(name, x):
    if x is None:
        return None
    try:
        x = float(x)
    except (TypeError, ValueError):
        raise SurveyError(f"{name} must be a positive number, not {x!r}") from None
    if not (math.isfinite(x) and x > 0):
        raise SurveyError(f"{name} must be a positive number, not {x!r}")
    return x


def _fit(method, coordinates, data, damping):
    """Fit the gridder to the block medians; returns (gridder, damping used, extra attrs)."""
    import verde as vd

    if method == "spline":
        return vd.Spline(damping=damping).fit(coordinates, data), damping, {}
    import harmonica as hm
    damping = EQS_DEFAULT_DAMPING if damping is None else damping
    # One thread: the machine is shared, and a few hundred sources do not need more.
    gridder = hm.EquivalentSources(damping=damping, parallel=False)
    gridder.fit((*coordinates, np.zeros_like(data)), data)
    return gridder, damping, {"eqs_depth_m": float(gridder.depth_)}


def _predict(gridder, method, east, north):
    if method == "spline":
        return gridder.predict((east, north))
    return gridder.predict((east, north, np.zeros_like(east)))


def _round_spacing(x):
    """The nearest (in ratio) of 1, 2, 2.5 or 5 times a power of ten (round spacings)."""
    power = 10.0 ** math.floor(math.log10(x))
    candidates = [m * power for m in (1.0, 2.0, 2.5, 5.0, 10.0)]
    return min(candidates, key=lambda c: abs(math.log(c / x)))


def grid_anomaly(north, east, value, *, spacing_m=None, method="spline", damping=None,
                 line_spacing_m=None, mask_m=None):
    """Grid a levelled anomaly sampled along flight lines.

    ``north``, ``east`` (m, local, from the survey's origin) and ``value`` (nT) are 1-D
    arrays of one length; samples with a NaN in any of them are dropped. ``method`` is
    ``"spline"`` (``verde.Spline``) or ``"eqs"`` (``harmonica.EquivalentSources``);
    ``damping`` is the gridder's relative ridge damping (None: the spline interpolates the
    block medians exactly, the equivalent sources use ``EQS_DEFAULT_DAMPING``).
    ``spacing_m`` (default: a third of the line spacing, rounded to the nearest 1, 2, 2.5
    or 5 times a power of ten: 10 m for lines 30 m apart) is the grid's spacing,
    ``line_spacing_m`` overrides the spacing measured by :func:`line_spacing`, ``mask_m``
    (default: one line spacing) the distance beyond which nodes are blanked.

    Returns an ``xarray.Dataset`` with one variable ``anomaly`` (nT, float64, NaN where
    masked) on dims ``("northing", "easting")`` (local metres, ascending, nodes on
    multiples of the spacing from the data's south-west corner) and attrs ``method``,
    ``spacing_m``, ``line_spacing_m``, ``line_direction_deg``, ``block_m``, ``mask_m``,
    ``damping`` (absent when None), ``n_data``, ``n_blocks``, ``misfit_rms_nT`` (the
    gridder's RMS misfit at every finite sample, not only at the block medians),
    ``coverage`` (the fraction of nodes not masked), ``grid_crs = "local"`` (not ``crs``,
    which rioxarray takes for its own) and, for
    ``"eqs"``, ``eqs_depth_m``. :func:`grid_summary` turns the attrs into a dict.
    """
    import verde as vd
    import xarray as xr

    if method not in METHODS:
        raise SurveyError(f"gridding method must be one of {METHODS}, not {method!r}")
    spacing_m = _positive("grid spacing", spacing_m)
    line_spacing_m = _positive("line spacing", line_spacing_m)
    mask_m = _positive("mask distance", mask_m)
    if damping is not None:
        damping = float(damping)
        if not (math.isfinite(damping) and damping >= 0):
            raise SurveyError(f"damping must be a number >= 0 or None, not {damping!r}")
    north, east, value = _check_points(north, east, value)

    spacing_lines, direction, _ = line_spacing(north, east)
    if line_spacing_m is None:
        line_spacing_m = spacing_lines
    spacing = spacing_m if spacing_m is not None else _round_spacing(line_spacing_m / 3.0)
    block = line_spacing_m / 3.0
    mask_distance = mask_m if mask_m is not None else line_spacing_m

    region = vd.get_region((east, north))
    shape = (int(math.floor((region[3] - region[2]) / spacing)) + 1,
             int(math.floor((region[1] - region[0]) / spacing)) + 1)
    if shape[0] * shape[1] > MAX_NODES:
        raise SurveyError(f"grid spacing {spacing:g} m is too fine for a "
                          f"{region[1] - region[0]:.0f} m x {region[3] - region[2]:.0f} m "
                          f"survey ({shape[0]} x {shape[1]} nodes, at most {MAX_NODES})")
    grid_east = region[0] + spacing * np.arange(shape[1])
    grid_north = region[2] + spacing * np.arange(shape[0])

    reducer = vd.BlockReduce(np.median, spacing=block, center_coordinates=False)
    block_coordinates, block_value = reducer.filter((east, north), value)
    gridder, damping, extra = _fit(method, block_coordinates, block_value, damping)

    mesh_east, mesh_north = np.meshgrid(grid_east, grid_north)
    anomaly = _predict(gridder, method, mesh_east, mesh_north)
    far = vd.distance_mask((east, north), mask_distance, coordinates=(mesh_east, mesh_north))
    anomaly = np.where(far, anomaly, np.nan)
    misfit = _predict(gridder, method, east, north) - value

    attrs = {"method": method, "spacing_m": float(spacing),
             "line_spacing_m": float(line_spacing_m), "line_direction_deg": direction,
             "block_m": float(block), "mask_m": float(mask_distance),
             "n_data": int(value.size), "n_blocks": int(block_value.size),
             "misfit_rms_nT": float(np.sqrt(np.mean(misfit ** 2))),
             "coverage": float(np.mean(far)), "grid_crs": "local", **extra}
    if damping is not None:
        attrs["damping"] = float(damping)
    return xr.Dataset(
        {"anomaly": ((_NORTHING, _EASTING), anomaly,
                     {"units": "nT", "long_name": "total-field anomaly"})},
        coords={_NORTHING: (_NORTHING, grid_north,
                            {"units": "m", "long_name": "north of the survey origin"}),
                _EASTING: (_EASTING, grid_east,
                           {"units": "m", "long_name": "east of the survey origin"})},
        attrs=attrs)


def grid_summary(ds):
    """The grid's description for the report, a dict: ``method``, ``spacing_m``,
    ``shape`` (rows, columns), ``damping`` (None when undamped), ``misfit_rms_nT``,
    ``line_spacing_m``, ``block_m``, ``mask_m``, ``n_data``, ``n_blocks``, ``coverage``,
    ``crs`` ("local" or "EPSG:nnnnn") and, for equivalent sources, ``eqs_depth_m``."""
    a = ds.attrs
    out = {"method": a["method"], "spacing_m": a["spacing_m"],
           "shape": tuple(int(n) for n in ds["anomaly"].shape),
           "damping": a.get("damping"), "misfit_rms_nT": a["misfit_rms_nT"],
           "line_spacing_m": a["line_spacing_m"], "block_m": a["block_m"],
           "mask_m": a["mask_m"], "n_data": int(a["n_data"]), "n_blocks": int(a["n_blocks"]),
           "coverage": a["coverage"], "crs": a["grid_crs"]}
    if "eqs_depth_m" in a:
        out["eqs_depth_m"] = a["eqs_depth_m"]
    return {k: (v.item() if isinstance(v, np.generic) else v) for k, v in out.items()}


# -- UTM -----------------------------------------------------------------------------------

def utm_epsg(lat, lon):
    """EPSG code of the WGS 84 UTM zone holding (lat, lon): 326zz north, 327zz south,
    with the Norway (32V) and Svalbard (31X-37X) exceptions."""
    if not (-80.0 <= lat <= 84.0) or not (-180.0 <= lon <= 180.0):
        raise SurveyError(f"no UTM zone at latitude {lat:g}, longitude {lon:g} "
                          "(UTM covers 80 S to 84 N)")
    zone = min(int(math.floor((lon + 180.0) / 6.0)) + 1, 60)
    if 56.0 <= lat < 64.0 and 3.0 <= lon < 12.0:
        zone = 32
    elif lat >= 72.0 and 0.0 <= lon < 42.0:
        zone = 31 if lon < 9 else 33 if lon < 21 else 35 if lon < 33 else 37
    return (32600 if lat >= 0 else 32700) + zone


def to_utm(ds, lat0, lon0):
    """The grid resampled onto a regular UTM grid (WGS 84, the zone of the origin).

    ``ds`` is a grid from :func:`grid_anomaly` in local metres from (lat0, lon0). The UTM
    nodes keep the grid's spacing, sit on multiples of it, and cover the local grid; each
    is taken back to local metres (pyproj, then the flat-earth formula) and interpolated
    bilinearly (NaN where any neighbour is masked or outside). Bilinear resampling, not a
    new fit: the UTM grid is the local one turned by the meridian convergence (a fraction
    of a degree), and the field is smooth on the grid's scale.

    Returns a Dataset like the input (dims ``("northing", "easting")``, now UTM metres,
    ascending) with its CRS written by rioxarray (a ``spatial_ref`` coordinate, the
    variable's ``grid_mapping``) and attrs ``grid_crs = "EPSG:nnnnn"``, ``utm_epsg``,
    ``origin_lat_deg``, ``origin_lon_deg``.
    """
    import pyproj
    import xarray as xr
    from scipy.interpolate import RegularGridInterpolator

    if ds.attrs.get("grid_crs", "local") != "local":
        raise SurveyError(f"the grid is already in {ds.attrs['grid_crs']}, not local metres")
    lat0, lon0 = float(lat0), float(lon0)
    epsg = utm_epsg(lat0, lon0)
    forward = pyproj.Transformer.from_crs("EPSG:4326", f"EPSG:{epsg}", always_xy=True)
    spacing = float(ds.attrs["spacing_m"])
    north, east = ds[_NORTHING].values, ds[_EASTING].values
    metres_east = METRES_PER_DEGREE * math.cos(math.radians(lat0))

    corner_north = np.array([north[0], north[0], north[-1], north[-1]])
    corner_east = np.array([east[0], east[-1], east[0], east[-1]])
    x, y = forward.transform(lon0 + corner_east / metres_east,
                             lat0 + corner_north / METRES_PER_DEGREE)
    utm_east = spacing * np.arange(math.floor(x.min() / spacing), math.ceil(x.max() / spacing) + 1)
    utm_north = spacing * np.arange(math.floor(y.min() / spacing), math.ceil(y.max() / spacing) + 1)
    mesh_x, mesh_y = np.meshgrid(utm_east, utm_north)
    lon, lat = forward.transform(mesh_x, mesh_y, direction="INVERSE")
    local = np.column_stack([((lat - lat0) * METRES_PER_DEGREE).ravel(),
                             ((lon - lon0) * metres_east).ravel()])
    interpolate = RegularGridInterpolator((north, east), ds["anomaly"].values,
                                          bounds_error=False, fill_value=np.nan)
    anomaly = interpolate(local).reshape(mesh_x.shape)

    attrs = {**ds.attrs, "grid_crs": f"EPSG:{epsg}", "utm_epsg": int(epsg),
             "origin_lat_deg": lat0, "origin_lon_deg": lon0}
    attrs["coverage"] = float(np.mean(np.isfinite(anomaly)))
    out = xr.Dataset(
        {"anomaly": ((_NORTHING, _EASTING), anomaly, dict(ds["anomaly"].attrs))},
        coords={_NORTHING: (_NORTHING, utm_north,
                            {"units": "m", "standard_name": "projection_y_coordinate",
                             "long_name": "UTM northing"}),
                _EASTING: (_EASTING, utm_east,
                           {"units": "m", "standard_name": "projection_x_coordinate",
                            "long_name": "UTM easting"})},
        attrs=attrs)
    _register_rio()
    out = out.rio.set_spatial_dims(x_dim=_EASTING, y_dim=_NORTHING)
    return out.rio.write_crs(f"EPSG:{epsg}")


# -- files ---------------------------------------------------------------------------------

def _register_rio():
    """Import rioxarray, which registers the ``.rio`` accessor on xarray objects."""
    importlib.import_module("rioxarray")


def write_netcdf(ds, path):
    """Write the grid (local or UTM) as NetCDF-4 through h5netcdf; returns the path."""
    path = Path(path)
    ds.to_netcdf(path, engine="h5netcdf")
    return path


def read_netcdf(path):
    """Read a grid written by :func:`write_netcdf`, the CRS restored (``decode_coords="all"``
    makes ``spatial_ref`` a coordinate again, so ``ds.rio.crs`` works for a UTM grid)."""
    import xarray as xr

    with xr.open_dataset(path, engine="h5netcdf", decode_coords="all") as ds:
        ds = ds.load()
    if ds.attrs.get("grid_crs", "local") != "local":
        _register_rio()
        ds = ds.rio.set_spatial_dims(x_dim=_EASTING, y_dim=_NORTHING)
    return ds


def write_geotiff(ds, path):
    """Write a UTM grid from :func:`to_utm` as a one-band float32 GeoTIFF (rioxarray):
    north up, its CRS, nodata NaN, the grid's attrs as tags. Returns the path."""
    if ds.attrs.get("grid_crs", "local") == "local":
        raise SurveyError("a GeoTIFF needs a projected grid: call to_utm first")
    _register_rio()
    band = ds["anomaly"].astype(np.float32).sortby(_NORTHING, ascending=False)
    band = band.rio.set_spatial_dims(x_dim=_EASTING, y_dim=_NORTHING)
    band = band.rio.write_crs(ds.attrs["grid_crs"]).rio.write_nodata(np.nan, encoded=False)
    band.attrs.update({k: v for k, v in ds.attrs.items() if isinstance(v, (str, int, float))})
    path = Path(path)
    band.rio.to_raster(path, driver="GTiff")      # any file name (a staged .tmp too)
    return path


# -- map -----------------------------------------------------------------------------------

def map_plot(ds, tracks, path, *, sources=None, title=None):
    """Draw the grid as a PNG map: the anomaly (a diverging colour map symmetric about
    zero) with a colour bar, the flight lines and, optionally, true source positions.

    ``tracks``: an iterable of ``(north, east)`` array pairs, one per line, in the grid's
    coordinates (None or empty: no lines); ``sources``: an iterable of ``(north, east)``
    pairs drawn as star markers. Uses a bare Agg figure (no pyplot state). Returns the path.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    anomaly = ds["anomaly"].values
    north, east = ds[_NORTHING].values, ds[_EASTING].values
    limit = float(np.nanmax(np.abs(anomaly))) if np.isfinite(anomaly).any() else 1.0
    limit = limit if limit > 0 else 1.0
    half = 0.5 * float(ds.attrs.get("spacing_m", 1.0))
    fig = Figure(figsize=(7.0, 6.0), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    image = ax.imshow(anomaly, origin="lower", cmap="RdBu_r", vmin=-limit, vmax=limit,
                      extent=(east[0] - half, east[-1] + half, north[0] - half, north[-1] + half),
                      interpolation="nearest")
    fig.colorbar(image, ax=ax, label="total-field anomaly (nT)")
    for k, (line_north, line_east) in enumerate(tracks or ()):
        ax.plot(line_east, line_north, color="k", linewidth=0.6, alpha=0.7,
                label="flight lines" if k == 0 else None)
    if sources is not None and len(sources):
        src = np.asarray(sources, dtype=float).reshape(-1, 2)
        ax.plot(src[:, 1], src[:, 0], linestyle="none", marker="*", markersize=14,
                markerfacecolor="gold", markeredgecolor="k", label="true sources")
    crs = ds.attrs.get("grid_crs", "local")
    unit = "m from origin" if crs == "local" else f"m, {crs}"
    ax.set_xlabel(f"easting ({unit})")
    ax.set_ylabel(f"northing ({unit})")
    ax.set_aspect("equal")
    ax.ticklabel_format(useOffset=False, style="plain")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper right", fontsize="small")
    if title:
        ax.set_title(title)
    path = Path(path)
    fig.savefig(path, format="png", dpi=110)
    return path


# -- peak ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Peak:
    """The grid node with the largest |anomaly|: its signed value and coordinates (in the
    grid's coordinates: local or UTM metres)."""
    amplitude_nT: float
    northing: float
    easting: float

    def as_dict(self):
        return {"amplitude_nT": self.amplitude_nT, "northing": self.northing,
                "easting": self.easting}


def peak(ds):
    """The :class:`Peak` of a grid (NaN nodes ignored); SurveyError if all are NaN."""
    anomaly = ds["anomaly"].values
    if not np.isfinite(anomaly).any():
        raise SurveyError("the grid has no value: every node is masked")
    row, column = np.unravel_index(np.nanargmax(np.abs(anomaly)), anomaly.shape)
    return Peak(float(anomaly[row, column]), float(ds[_NORTHING].values[row]),
                float(ds[_EASTING].values[column]))
