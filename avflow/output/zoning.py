"""Hazard zoning from peak pressure and return period: red, blue and yellow zones by the
intensity-frequency rule of the Swiss avalanche guideline, as a paletted GeoTIFF and a
legend.

The rule (:func:`zone_map`), for each pixel and each scenario of return period T (years)
that reached it with peak pressure p (kPa):

- red: p >= 30 kPa with T <= 300 years, or any flow with T <= 30 years;
- blue: 3 <= p < 30 kPa with 30 < T <= 300 years;
- yellow: p < 3 kPa with 30 < T <= 300 years, or any flow with T > 300 years;
- no zone (white): no scenario reached the pixel.

A pixel takes the most severe zone over the scenarios. The limits are those of BFF/SLF
(1984), *Richtlinien zur Berücksichtigung der Lawinengefahr bei raumwirksamen
Tätigkeiten*, as the SLF summarises them (30 kN/m2 between strong and medium intensity;
scenarios of 30, 100 and 300 years); the 3 kPa limit of the yellow zone is the guideline's
limit for powder avalanches, applied here to the flow's pressure. Every limit is a
parameter (:class:`ZoningRule`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from avflow.errors import AvflowError

import numpy as np

#: Zone codes of the GeoTIFF (255: outside the DEM).
NONE, YELLOW, BLUE, RED = 0, 1, 2, 3
NODATA = 255
ZONE_NAMES = {NONE: "no zone", YELLOW: "yellow", BLUE: "blue", RED: "red"}
#: Palette (RGBA): white, the zoning colours of Swiss and Austrian hazard maps.
ZONE_COLORS = {NONE: (255, 255, 255, 255), YELLOW: (255, 230, 0, 255),
               BLUE: (0, 112, 255, 255), RED: (230, 0, 0, 255)}

REFERENCE = ("BFF/SLF (1984): Richtlinien zur Berücksichtigung der Lawinengefahr bei "
             "raumwirksamen Tätigkeiten. Bundesamt für Forstwesen, Eidgenössisches Institut "
             "für Schnee- und Lawinenforschung, Bern/Davos")


class ZoningError(AvflowError):
    """Inputs that cannot make a zoning map (one line; exit 2)."""


@dataclass(frozen=True)
class ZoningRule:
    """The limits of the rule (kPa, years)."""

    red_kpa: float = 30.0  #: strong intensity from here (red up to rare_years)
    yellow_kpa: float = 3.0  #: weak intensity below this (yellow beyond frequent_years)
    frequent_years: float = 30.0  #: any flow this frequent is red
    rare_years: float = 300.0  #: beyond: yellow whatever the pressure

    def zone(self, pressure_kpa: np.ndarray, reached: np.ndarray, years: float) -> np.ndarray:
        """The zone of each pixel for one scenario of return period ``years``."""
        p = np.where(reached, np.nan_to_num(pressure_kpa, nan=0.0), 0.0)
        z = np.full(p.shape, NONE, dtype=np.uint8)
        if years > self.rare_years:
            z[reached] = YELLOW
            return z
        if years <= self.frequent_years:
            z[reached] = RED
            return z
        z[reached & (p < self.yellow_kpa)] = YELLOW
        z[reached & (p >= self.yellow_kpa)] = BLUE
        z[reached & (p >= self.red_kpa)] = RED
        return z

    def describe(self) -> list[tuple[int, str]]:
        f, r = f"{self.frequent_years:g}", f"{self.rare_years:g}"
        return [
            (RED, f"red: p \u2265 {self.red_kpa:g} kPa with T \u2264 {r} years, "
                  f"or reached with T \u2264 {f} years"),
            (BLUE, f"blue: {self.yellow_kpa:g} \u2264 p < {self.red_kpa:g} kPa with "
                   f"{f} < T \u2264 {r} years"),
            (YELLOW, f"yellow: p < {self.yellow_kpa:g} kPa with {f} < T \u2264 {r} years, "
                     f"or reached only with T > {r} years"),
            (NONE, "no zone: not reached by any scenario"),
        ]


def zone_map(scenarios, rule: ZoningRule = ZoningRule()) -> np.ndarray:
    """The zones of the pixels: ``scenarios`` is a list of ``(years, pressure_kpa,
    reached)`` on one grid; the most severe zone over them (NaN pressure: not reached)."""
    zones = None
    for years, p, reached in scenarios:
        z = rule.zone(np.asarray(p, dtype=float), np.asarray(reached, dtype=bool), years)
        zones = z if zones is None else np.maximum(zones, z)
    return zones


def run_scenario(path) -> tuple:
    """``(pressure_kpa, reached, x, y, crs_wkt)`` of a run file written by avflow run (a
    grid): peak pressure where the peak thickness passed the runout threshold."""
    import xarray as xr

    path = Path(path)
    try:
        ds = xr.open_dataset(path, decode_times=False)
    except Exception as err:  # noqa: BLE001 - not a NetCDF file: one line
        raise ZoningError(f"{path}: cannot be read as a run file ({type(err).__name__})") \
            from None
    with ds:
        if "peak_pressure" not in ds or ds["peak_pressure"].dims != ("y", "x"):
            raise ZoningError(f"{path}: not a run file on a map (no peak_pressure on (y, x))")
        p = np.asarray(ds["peak_pressure"].values, dtype=float)
        if ds["peak_pressure"].attrs.get("units", "Pa") == "Pa":
            p = p / 1000.0
        h = np.nan_to_num(np.asarray(ds["peak_thickness"].values, dtype=float))
        threshold = float(ds.attrs.get("runout_threshold_m", 0.0) or 0.0)
        reached = h > threshold
        inside = np.isfinite(np.asarray(ds["bed_elevation"].values, dtype=float)) \
            if "bed_elevation" in ds else np.ones(p.shape, bool)
        wkt = ds["crs"].attrs.get("crs_wkt") if "crs" in ds else None
        return p, reached & inside, inside, ds["x"].values, ds["y"].values, wkt


def zoning_from_runs(runs: dict, rule: ZoningRule = ZoningRule()) -> dict:
    """``runs``: return period (years) -> run file(s) (a path or a list: the largest
    pressure of the list, e.g. several releases of one return period). Returns the zones,
    x, y, the CRS and the inside mask."""
    scenarios, grid = [], None
    for years, paths in sorted(runs.items()):
        for path in [paths] if isinstance(paths, (str, Path)) else paths:
            p, reached, inside, x, y, wkt = run_scenario(path)
            if grid is None:
                grid = (x, y, wkt, inside, path)
            elif not (np.array_equal(x, grid[0]) and np.array_equal(y, grid[1])):
                raise ZoningError(f"{path}: its map is not the grid of {grid[4]} (the runs "
                                  "of a zoning share one grid: the same DEM and grid.dx)")
            scenarios.append((years, p, reached))
    zones = zone_map(scenarios, rule)
    x, y, wkt, inside, _ = grid
    return {"zones": zones, "x": x, "y": y, "crs_wkt": wkt, "inside": inside}


def write_zoning(result: dict, path, rule: ZoningRule, periods, title: str = "") -> list:
    """The zones as a paletted GeoTIFF ``path`` (uint8: 0 none, 1 yellow, 2 blue, 3 red,
    255 outside the DEM) and its legend ``<stem>_legend.png``; returns both paths."""
    from avflow.terrain.raster import write_tif

    path = Path(path)
    zones = np.where(result["inside"], result["zones"], NODATA).astype(float)
    zones[~result["inside"]] = np.nan
    tags = {"rule": "; ".join(text for _, text in rule.describe()),
            "return_periods_years": ", ".join(f"{t:g}" for t in periods),
            "reference": REFERENCE,
            **{f"class_{code}": name for code, name in ZONE_NAMES.items()}}
    write_tif(path, zones, result["x"], result["y"], result["crs_wkt"], dtype="uint8",
              nodata=NODATA, colormap=ZONE_COLORS, description="hazard zone", tags=tags)
    legend = path.with_name(path.stem + "_legend.png")
    plot_legend(legend, rule, periods, zone_areas(result), title)
    return [path, legend]


def zone_areas(result: dict) -> dict:
    """Area of each zone (m^2, map area)."""
    x, y = result["x"], result["y"]
    cell = abs(float(x[1] - x[0]) * float(y[1] - y[0]))
    z = np.where(result["inside"], result["zones"], NODATA)
    return {code: float(np.count_nonzero(z == code)) * cell for code in (RED, BLUE, YELLOW)}


def plot_legend(path, rule: ZoningRule, periods, areas: dict, title: str = "") -> Path:
    """The legend: a patch per zone with its rule and area, the return periods used and the
    guideline; written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    from avflow.files import atomic_write

    rows = rule.describe()
    fig, ax = plt.subplots(figsize=(7.2, 0.5 * len(rows) + 1.3))
    ax.set_axis_off()
    ax.set_xlim(0, 10)
    ax.set_ylim(-1.6, len(rows) + 0.2)
    for k, (code, text) in enumerate(rows):
        yk = len(rows) - 1 - k
        rgba = tuple(v / 255 for v in ZONE_COLORS[code])
        ax.add_patch(Rectangle((0.1, yk + 0.15), 0.6, 0.6, facecolor=rgba, edgecolor="0.3"))
        area = f"  ({areas[code] / 1e4:.2f} ha)" if code in areas else ""
        ax.text(0.9, yk + 0.45, text + area, va="center", fontsize=8.5)
    ax.text(0.1, -0.45, "p: peak pressure; T: return period of the scenario; a pixel takes "
            "the most severe zone. Scenarios: " + ", ".join(f"{t:g}" for t in periods)
            + " years.", fontsize=7.5, va="center")
    ax.text(0.1, -1.1, "Limits after BFF/SLF (1984), Richtlinien zur Berücksichtigung der "
            "Lawinengefahr\nbei raumwirksamen Tätigkeiten.", fontsize=7.5, va="center",
            style="italic")
    ax.set_title(title or "hazard zones", fontsize=10, loc="left")

    def write(tmp):
        fig.savefig(tmp, dpi=110, format="png", bbox_inches="tight")

    try:
        return atomic_write(path, write)
    finally:
        plt.close(fig)
