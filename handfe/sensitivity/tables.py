"""Tables and charts of a sensitivity study, built only from ``<out>/cases/*.json``.

Files written into ``<out>/`` (rank 0):

* ``table_<parameter>.csv`` - the source's layout: one row per (metric, region), columns
  ``metric, region, unit, baseline`` then, per level, ``<L>%`` (value) and ``<L>% change``
  (% change from the baseline). Empty cell = case missing, failed or skipped.
* ``sensitivity_long.csv`` - ``parameter, level_pct, region, metric, value, pct_change,
  ratio_of_pct_change`` (+ ``case_id, status, flag``); the baseline rows have parameter
  ``baseline``, level 0. ratio_of_pct_change = pct_change / level_pct.
* ``refits.csv`` - material refits: ``parameter, level_pct, mu1_MPa..mu3_MPa, alpha1..alpha3,
  fit_rms_pct, fit_max_pct, mu_vs_scaled_pct, alpha_change_pct, stable, used, problem``.
* ``status.csv`` - every case: ``case_id, parameter, level_pct, status, wall_s, ranks,
  finished_utc, flag, error``.
* ``tornado_<metric>.png`` - per metric, one panel per region: % change of the output at the
  lowest and highest level of each parameter, parameters sorted by swing.

Numbers are written with 6 significant digits; everything is a pure function of the case files,
so the same files give byte-identical CSVs.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from handfe.io import write_csv
from handfe.sensitivity.driver import BASELINE, read_case, study_cases
from handfe.sensitivity.study import Study

UNITS = {"contact_area_mm2": "mm^2", "loaded_area_mm2": "mm^2", "mean_pressure_kPa": "kPa",
         "peak_pressure_kPa": "kPa", "normal_force_N": "N", "tangential_force_N": "N",
         "deflection_mm": "mm"}


def _f(x: float | None) -> str:
    return "" if x is None or not math.isfinite(x) else f"{x:.6g}"


def _value(rec: dict[str, Any] | None, region: str, metric: str) -> float | None:
    if not rec or rec.get("status") != "ok":
        return None
    v = rec.get("regions", {}).get(region, {}).get(metric)
    return float(v) if isinstance(v, int | float) else None


def _pct(v: float | None, v0: float | None) -> float | None:
    if v is None or v0 is None or v0 == 0.0:
        return None
    return (v - v0) / abs(v0) * 100.0


def _level_label(lv: float) -> str:
    return f"{lv:+g}%"


def build_tables(study: Study, out_dir: Path | str, *,
                 charts: bool = True) -> tuple[dict[str, str], dict[str, str]]:
    """Write all tables (and, with ``charts``, the tornado PNGs); return ({name: path},
    {case_id: status}). Rank 0 only."""
    out_dir = Path(out_dir)
    cases = study_cases(study)
    recs = {c.id: read_case(out_dir, c.id) for c in cases}
    statuses = {c.id: (recs[c.id] or {}).get("status", "missing") for c in cases}
    base = recs[BASELINE]
    paths: dict[str, str] = {}
    regions, metrics = study.regions, study.metrics

    long_rows: list[dict[str, Any]] = []
    for r in regions:
        for m in metrics:
            v0 = _value(base, r, m)
            long_rows.append({"parameter": BASELINE, "level_pct": "0", "region": r, "metric": m,
                              "value": _f(v0), "pct_change": _f(0.0 if v0 is not None else None),
                              "ratio_of_pct_change": "", "case_id": BASELINE,
                              "status": statuses[BASELINE], "flag": (base or {}).get("flag", "")})
    for p in study.parameters:
        levels = study.levels(p)
        rows = []
        for m in metrics:
            for r in regions:
                v0 = _value(base, r, m)
                row: dict[str, Any] = {"metric": m, "region": r, "unit": UNITS.get(m, ""),
                                       "baseline": _f(v0)}
                for lv in levels:
                    c = next(c for c in cases if c.parameter == p and c.level_pct == lv)
                    rec = recs[c.id]
                    v = _value(rec, r, m)
                    pc = _pct(v, v0)
                    row[_level_label(lv)] = _f(v)
                    row[f"{_level_label(lv)} change"] = _f(pc)
                    long_rows.append({
                        "parameter": p, "level_pct": f"{lv:g}", "region": r, "metric": m,
                        "value": _f(v), "pct_change": _f(pc),
                        "ratio_of_pct_change": _f(None if pc is None else pc / lv),
                        "case_id": c.id, "status": statuses[c.id],
                        "flag": (rec or {}).get("flag", "")})
                rows.append(row)
        path = out_dir / f"table_{p}.csv"
        write_csv(path, rows)
        paths[f"table_{p}"] = str(path)
    path = out_dir / "sensitivity_long.csv"
    write_csv(path, long_rows)
    paths["long"] = str(path)

    refit_rows = []
    for c in cases:
        rec = recs[c.id]
        rf = (rec or {}).get("refit")
        if not rf:
            continue
        row = {"parameter": c.parameter, "level_pct": f"{c.level_pct:g}", "case_id": c.id}
        for i, v in enumerate(rf["mu_MPa"]):
            row[f"mu{i + 1}_MPa"] = _f(v)
        for i, v in enumerate(rf["alpha"]):
            row[f"alpha{i + 1}"] = _f(v)
        row.update(nu=_f(rf["nu"]), fit_rms_pct=_f(rf["fit_rms_pct"]),
                   fit_max_pct=_f(rf["fit_max_pct"]),
                   mu_vs_scaled_pct=_f(rf["mu_vs_scaled_pct"]),
                   alpha_change_pct=_f(rf["alpha_change_pct"]), stable=int(bool(rf["stable"])),
                   used=int(statuses[c.id] == "ok"), status=statuses[c.id],
                   problem=rf.get("problem", ""))
        refit_rows.append(row)
    if any(p in ("skin", "subcutaneous") for p in study.parameters):
        path = out_dir / "refits.csv"
        write_csv(path, refit_rows)
        paths["refits"] = str(path)

    status_rows = []
    for c in cases:
        rec = recs[c.id] or {}
        status_rows.append({"case_id": c.id, "parameter": c.parameter,
                            "level_pct": f"{c.level_pct:g}", "status": statuses[c.id],
                            "wall_s": _f(rec.get("wall_s")), "ranks": rec.get("ranks", ""),
                            "finished_utc": rec.get("finished_utc", ""),
                            "flag": rec.get("flag", ""), "error": rec.get("error", "")})
    path = out_dir / "status.csv"
    write_csv(path, status_rows)
    paths["status"] = str(path)

    for m in metrics if charts else ():
        path = out_dir / f"tornado_{m}.png"
        tornado_png(study, long_rows, m, path)
        paths[f"tornado_{m}"] = str(path)
    return paths, statuses


def tornado_png(study: Study, long_rows: list[dict[str, Any]], metric: str, path: Path) -> None:
    """Tornado chart of ``metric``: per region, bars of the % change at each parameter's lowest
    (blue) and highest (red) level; hatched = flagged refit; missing cases have no bar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    regions = list(study.regions)
    ncol = min(3, len(regions))
    nrow = math.ceil(len(regions) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(max(4.6 * ncol, 6.0), 1.2 + 0.45 * nrow *
                                                  (len(study.parameters) + 2)), squeeze=False)
    for k, r in enumerate(regions):
        ax = axes[k // ncol][k % ncol]
        bars = []
        for p in study.parameters:
            lv = study.levels(p)
            lo, hi = lv[0], lv[-1]

            def get(level, p=p, r=r):
                row = next((x for x in long_rows if x["parameter"] == p and x["region"] == r
                            and x["metric"] == metric and float(x["level_pct"]) == level), None)
                if row is None or row["pct_change"] == "":
                    return None, False
                return float(row["pct_change"]), bool(row["flag"])

            (vlo, flo), (vhi, fhi) = get(lo), get(hi)
            swing = abs((vhi or 0.0) - (vlo or 0.0))
            bars.append((swing, p, lo, vlo, flo, hi, vhi, fhi))
        bars.sort(key=lambda b: b[0])
        for y, (_, _p, lo, vlo, flo, hi, vhi, fhi) in enumerate(bars):
            for v, lvl, flag, col in ((vlo, lo, flo, "tab:blue"), (vhi, hi, fhi, "tab:red")):
                if v is None:
                    continue
                ax.barh(y, v, height=0.6, color=col, alpha=0.8,
                        hatch="//" if flag else None)
                ax.text(v, y + (0.18 if col == "tab:red" else -0.18), f" {lvl:+g}%: {v:+.2g}% ",
                        va="center", ha="left" if v >= 0 else "right", fontsize=7)
        ax.set_yticks(range(len(bars)))
        ax.set_yticklabels([b[1] for b in bars])
        ax.axvline(0.0, color="k", lw=0.8)
        ax.set_title(r, fontsize=10)
        ax.set_xlabel(f"% change of {metric}")
        lim = max([abs(v) for b in bars for v in (b[3], b[6]) if v is not None] + [1.0])
        ax.set_xlim(-1.6 * lim, 1.6 * lim)
    for k in range(len(regions), nrow * ncol):
        axes[k // ncol][k % ncol].axis("off")
    from matplotlib.patches import Patch

    fig.legend(handles=[Patch(color="tab:blue", alpha=0.8, label="lowest level"),
                        Patch(color="tab:red", alpha=0.8, label="highest level"),
                        Patch(facecolor="white", edgecolor="k", hatch="//",
                              label="flagged refit")],
               loc="lower center", ncol=3, fontsize=8, frameon=False)
    fig.suptitle(f"{study.name}: % change of {metric} ({UNITS.get(metric, '')})", fontsize=10)
    fig.tight_layout(rect=(0, 0.07, 1, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
