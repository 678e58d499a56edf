#!/usr/bin/env python3
"""Generate the SYNTHETIC demo subject S01: surface EMG, MVC trials and data-glove recordings.

Nothing here is a measurement. The script builds recordings from known ground truth so that the
processing chain (``handfe.emg``, ``handfe.kinematics``) can be tested end to end. On purpose it
imports nothing from ``handfe`` and uses numpy only (no scipy.signal): the generator and the
processing chain share no code, so a round trip that recovers the truth really tests the chain.

Ground truth
------------
* Muscle forces: the brief's table (``reference/muscle_forces_by_grasp.csv``). Each grasp gets six
  trials whose forces vary from trial to trial (about 8 % SD) and average *exactly* to the table
  (integer arithmetic in mN). Each trial's forces are written beside its EMG file
  (``emg/<grasp>_NN.truth.csv``).
* Joint angles: nominal grasp postures (``GRASP_ANGLES_DEG`` below) with about 2 deg trial-to-trial
  variation, averaging exactly (0.01 deg) to the nominal posture; written beside each glove file.

EMG model (per muscle and trial, in microvolts)
-----------------------------------------------
``emg(t) = A_MVC * a(t) * c(t) + offset + hum(t) + motion(t) + floor(t)``, rounded to 1 uV, with

* ``a(t) = F_trial / F_MVC * p(t)``: activation, p = 0 at rest, raised-cosine ramps, 1 in the hold
  (force linear in EMG amplitude, the brief's model F = EMG/EMG_MVC * F_MVC);
* ``c(t)``: unit-RMS Gaussian noise with the Shwedyk et al. (1977) surface-EMG spectrum
  P(f) ~ fh^4 f^2 / ((f^2 + fl^2)(f^2 + fh^2)^2), fl = 60 Hz, fh = 120 Hz (peak near 80 Hz),
  made by spectral shaping with numpy's FFT. The carrier is rescaled to unit RMS in 250 ms blocks:
  the EMG *amplitude* then carries the force exactly, and what remains of the amplitude-estimation
  noise of real EMG (about 1.8 % * sqrt(2 s / T) for a T-second window without this step, measured
  with this spectrum) is about 0.5 % per 3.5 s window - small enough to test a 2 % round trip;
* nuisances the chain has to remove: a DC baseline offset (up to +-2 mV), 50 Hz mains hum with a
  150 Hz harmonic (20-80 uV, frequency 50 +- 0.02 Hz, in the pass band), a low-frequency motion
  artefact (< 6 Hz, 100-300 uV RMS, up to three times stronger mid-ramp), and a 2 uV RMS white
  amplifier noise floor.

MVC trials: per muscle, three 3-s maximal contractions (a = 1) in one file, with their hold windows
listed in ``mvc.csv``. F_MVC and the EMG amplitudes at MVC are invented, plausible numbers chosen
so that the grasp activations lie between 25 and 65 % MVC; they are not literature values.

Glove model
-----------
A 22-sensor resistive glove in the CyberGlove layout (3 flexion sensors per finger, thumb
rotation/MCP/IP/abduction, 3 finger-spread sensors, palm arch, wrist pitch and yaw), 100 Hz,
integer counts. A sensor reads ``count = (angle - offset_deg) / gain_deg_per_count + noise``; the
spread sensors read *differences* of abduction angles (index-middle, middle-ring, ring-little), so
little-finger abduction is a two-sensor combination in ``glove/calibration.csv``. The glove cannot
see middle-finger abduction, thumb MCP abduction, forearm pronation or the hand's position: those
DOFs stay at their neutral value (0) in the truth as well.

Typical grasp angles: finger flexion within the functional ranges of Hume et al. 1990 (J Hand Surg
15A:240; mean functional posture MCP 61, PIP 60, DIP 39 deg, thumb MCP 21, IP 18 deg) and Bain et
al. 2015 (J Hand Surg Eur 40:406; functional ROM MCP 19-71, PIP 23-87, DIP 10-64 deg), MCP flexion
increasing from the index to the little finger (Hayashi & Shimizu 2013, J Hand Ther 26:69). The
per-grasp numbers are this script's plausible choices within those ranges, not measurements.

Usage: ``python scripts/generate_synthetic_subject.py [--out subjects/S01] [--seed 20261122]``.
The output is a deterministic function of the seed (gzip headers carry no time stamp).
"""

from __future__ import annotations

import argparse
import csv
import gzip
import io
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
SEED = 20261122
FS_EMG = 2000.0  # Hz
FS_GLOVE = 100.0  # Hz
N_TRIALS = 6
GRASPS = ("cylindrical", "spherical", "precision")

# Trial timing (s): rest, ramp up, hold, ramp down, rest; onset jitters per trial.
T_TRIAL = 6.0
T_REST0, T_RAMP, T_HOLD = 0.5, 0.5, 4.0
ONSET_JITTER = 0.1
HOLD_MARGIN = 0.25  # s cut from each end of the hold for the stored hold window
# MVC: rest 1 s, then 3 x (ramp 0.5, hold 3, ramp 0.5, rest 1).
MVC_REPS, MVC_HOLD, MVC_REST = 3, 3.0, 1.0

# Invented F_MVC (N) and EMG RMS amplitude at MVC (uV) per muscle.
F_MVC_N = {"FDS": 420.0, "FDP": 360.0, "APL": 110.0, "APB": 22.0, "AP": 210.0, "FPB": 200.0,
           "FDI": 95.0, "SDI": 130.0, "TDI": 85.0}
A_MVC_UV = {"FDS": 450.0, "FDP": 520.0, "APL": 300.0, "APB": 280.0, "AP": 380.0, "FPB": 350.0,
            "FDI": 600.0, "SDI": 420.0, "TDI": 380.0}
FORCE_CV = 0.08  # trial-to-trial SD of force, relative

SYNTHETIC_NOTE = ("SYNTHETIC data generated by scripts/generate_synthetic_subject.py "
                  "(seed {seed}); NOT a recording of a person")

# Nominal hold postures (deg) of the DOFs the glove measures; see the module docstring.
GRASP_ANGLES_DEG = {
    "cylindrical": {  # power grasp of a ~50 mm cylinder: all fingers wrapped, thumb opposed
        "wrist_flexion": -15.0, "wrist_deviation": 5.0,
        "thumb_cmc_flexion": 30.0, "thumb_cmc_abduction": 45.0, "thumb_mcp_flexion": 25.0,
        "thumb_ip_flexion": 20.0,
        "index_mcp_flexion": 55.0, "index_mcp_abduction": 4.0, "index_pip_flexion": 60.0,
        "index_dip_flexion": 30.0,
        "middle_mcp_flexion": 60.0, "middle_pip_flexion": 65.0, "middle_dip_flexion": 35.0,
        "ring_mcp_flexion": 63.0, "ring_mcp_abduction": 3.0, "ring_pip_flexion": 65.0,
        "ring_dip_flexion": 35.0,
        "little_mcp_flexion": 66.0, "little_mcp_abduction": 8.0, "little_pip_flexion": 60.0,
        "little_dip_flexion": 30.0,
    },
    "spherical": {  # ~70 mm ball: fingers spread, less MCP flexion
        "wrist_flexion": -10.0, "wrist_deviation": 0.0,
        "thumb_cmc_flexion": 25.0, "thumb_cmc_abduction": 55.0, "thumb_mcp_flexion": 20.0,
        "thumb_ip_flexion": 15.0,
        "index_mcp_flexion": 40.0, "index_mcp_abduction": 12.0, "index_pip_flexion": 45.0,
        "index_dip_flexion": 25.0,
        "middle_mcp_flexion": 42.0, "middle_pip_flexion": 50.0, "middle_dip_flexion": 25.0,
        "ring_mcp_flexion": 45.0, "ring_mcp_abduction": 8.0, "ring_pip_flexion": 50.0,
        "ring_dip_flexion": 28.0,
        "little_mcp_flexion": 48.0, "little_mcp_abduction": 18.0, "little_pip_flexion": 45.0,
        "little_dip_flexion": 25.0,
    },
    "precision": {  # tripod pinch (thumb, index, middle); ring and little tucked
        "wrist_flexion": -15.0, "wrist_deviation": 0.0,
        "thumb_cmc_flexion": 35.0, "thumb_cmc_abduction": 50.0, "thumb_mcp_flexion": 20.0,
        "thumb_ip_flexion": 10.0,
        "index_mcp_flexion": 45.0, "index_mcp_abduction": 2.0, "index_pip_flexion": 50.0,
        "index_dip_flexion": 15.0,
        "middle_mcp_flexion": 50.0, "middle_pip_flexion": 55.0, "middle_dip_flexion": 20.0,
        "ring_mcp_flexion": 58.0, "ring_mcp_abduction": 2.0, "ring_pip_flexion": 70.0,
        "ring_dip_flexion": 40.0,
        "little_mcp_flexion": 62.0, "little_mcp_abduction": 5.0, "little_pip_flexion": 70.0,
        "little_dip_flexion": 40.0,
    },
}
REST_ANGLES_DEG = {  # relaxed, slightly flexed hand before and after the grasp
    "wrist_flexion": 0.0, "wrist_deviation": 0.0, "thumb_cmc_flexion": 10.0,
    "thumb_cmc_abduction": 20.0, "thumb_mcp_flexion": 10.0, "thumb_ip_flexion": 5.0,
    "index_mcp_flexion": 20.0, "index_mcp_abduction": 3.0, "index_pip_flexion": 25.0,
    "index_dip_flexion": 10.0, "middle_mcp_flexion": 20.0, "middle_pip_flexion": 25.0,
    "middle_dip_flexion": 10.0, "ring_mcp_flexion": 22.0, "ring_mcp_abduction": 3.0,
    "ring_pip_flexion": 25.0, "ring_dip_flexion": 10.0, "little_mcp_flexion": 25.0,
    "little_mcp_abduction": 6.0, "little_pip_flexion": 25.0, "little_dip_flexion": 10.0,
}
ANGLE_SD_DEG = 2.0

# Glove sensors (CyberGlove-style names) -> what each reads, as {dof: coefficient}.
# A spread sensor reads the difference of two abduction angles (middle abduction taken as 0).
SENSORS = {
    "thumb_rotation": {"thumb_cmc_flexion": 1.0},
    "thumb_mcp": {"thumb_mcp_flexion": 1.0},
    "thumb_ip": {"thumb_ip_flexion": 1.0},
    "thumb_abduction": {"thumb_cmc_abduction": 1.0},
    "index_mcp": {"index_mcp_flexion": 1.0},
    "index_pip": {"index_pip_flexion": 1.0},
    "index_dip": {"index_dip_flexion": 1.0},
    "middle_mcp": {"middle_mcp_flexion": 1.0},
    "middle_pip": {"middle_pip_flexion": 1.0},
    "middle_dip": {"middle_dip_flexion": 1.0},
    "ring_mcp": {"ring_mcp_flexion": 1.0},
    "ring_pip": {"ring_pip_flexion": 1.0},
    "ring_dip": {"ring_dip_flexion": 1.0},
    "little_mcp": {"little_mcp_flexion": 1.0},
    "little_pip": {"little_pip_flexion": 1.0},
    "little_dip": {"little_dip_flexion": 1.0},
    "index_middle_abduction": {"index_mcp_abduction": 1.0},
    "middle_ring_abduction": {"ring_mcp_abduction": 1.0},
    "ring_little_abduction": {"little_mcp_abduction": 1.0, "ring_mcp_abduction": -1.0},
    "palm_arch": {},
    "wrist_pitch": {"wrist_flexion": 1.0},
    "wrist_yaw": {"wrist_deviation": 1.0},
}
SENSOR_NOISE_COUNTS = 0.7


# ----------------------------------------------------------------------------- helpers

def read_table(path: Path) -> dict[str, dict[str, float]]:
    """muscle -> {grasp: force_N} from the brief's table."""
    with path.open() as fh:
        rows = list(csv.DictReader(line for line in fh if not line.startswith("#")))
    return {r["muscle"]: {g: float(r[f"{g}_N"]) for g in GRASPS} for r in rows}


def exact_mean_values(rng: np.random.Generator, mean: float, rel_sd: float, n: int,
                      quantum: float, abs_sd: float = 0.0) -> list[float]:
    """n values scattered around ``mean`` (relative SD ``rel_sd`` or absolute ``abs_sd``) that
    average exactly to ``mean`` in units of ``quantum`` (integer arithmetic)."""
    target = round(mean / quantum) * n
    sd = abs_sd if abs_sd else rel_sd * abs(mean)
    dev = rng.normal(0.0, sd, n)
    dev -= dev.mean()
    q = [round((mean + d) / quantum) for d in dev[:-1]]
    q.append(target - sum(q))
    return [v * quantum for v in q]


def smoothstep(x: np.ndarray) -> np.ndarray:
    """Raised cosine from 0 (x <= 0) to 1 (x >= 1)."""
    x = np.clip(x, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * x)


def hold_profile(t: np.ndarray, holds: list[tuple[float, float]], ramp: float) -> np.ndarray:
    """0 at rest, 1 within each (start, end) hold, raised-cosine ramps of ``ramp`` s around it."""
    p = np.zeros_like(t)
    for t0, t1 in holds:
        up = smoothstep((t - (t0 - ramp)) / ramp)
        down = 1.0 - smoothstep((t - t1) / ramp)
        p = np.maximum(p, np.minimum(up, down))
    return p


def shwedyk_carrier(rng: np.random.Generator, n: int, fs: float, block_s: float = 0.25,
                    fl: float = 60.0, fh: float = 120.0) -> np.ndarray:
    """Gaussian noise with the Shwedyk surface-EMG spectrum, unit RMS in blocks of block_s."""
    f = np.fft.rfftfreq(n, 1.0 / fs)
    psd = fh**4 * f**2 / ((f**2 + fl**2) * (f**2 + fh**2) ** 2)
    spec = (rng.normal(size=f.size) + 1j * rng.normal(size=f.size)) * np.sqrt(psd)
    x = np.fft.irfft(spec, n)
    b = int(round(block_s * fs))
    for i in range(0, n, b):
        seg = x[i:i + b]
        seg /= np.sqrt(np.mean(seg**2))
    return x


def lowfreq_noise(rng: np.random.Generator, n: int, fs: float, fmax: float) -> np.ndarray:
    """Unit-RMS Gaussian noise with a flat spectrum from 0.2 Hz to fmax (FFT mask)."""
    f = np.fft.rfftfreq(n, 1.0 / fs)
    spec = (rng.normal(size=f.size) + 1j * rng.normal(size=f.size)) * ((f > 0.2) & (f < fmax))
    x = np.fft.irfft(spec, n)
    return x / np.sqrt(np.mean(x**2))


def nuisances(rng: np.random.Generator, t: np.ndarray, ramp_weight: np.ndarray) -> np.ndarray:
    """Baseline offset + mains hum (50 Hz and 150 Hz) + motion artefact + noise floor (uV)."""
    n = t.size
    offset = rng.uniform(-2000.0, 2000.0)
    f_mains = 50.0 + rng.uniform(-0.02, 0.02)
    a_hum = rng.uniform(20.0, 80.0)
    hum = a_hum * (np.sin(2 * np.pi * f_mains * t + rng.uniform(0, 2 * np.pi))
                   + 0.3 * np.sin(2 * np.pi * 3 * f_mains * t + rng.uniform(0, 2 * np.pi)))
    motion = rng.uniform(100.0, 300.0) * lowfreq_noise(rng, n, FS_EMG, 6.0) * (1 + 2 * ramp_weight)
    floor = rng.normal(0.0, 2.0, n)
    return offset + hum + motion + floor


def write_text(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".gz":
        with path.open("wb") as raw, gzip.GzipFile(filename="", mode="wb", fileobj=raw,
                                                   mtime=0, compresslevel=9) as gz:
            gz.write(text.encode())
    else:
        path.write_text(text)


def timeseries_csv(note: str, header: list[str], t: np.ndarray, cols: list[np.ndarray],
                   time_fmt: str) -> str:
    buf = io.StringIO()
    buf.write(f"# {note}\n")
    buf.write(",".join(header) + "\n")
    data = np.column_stack([t] + [np.rint(c) for c in cols])
    fmt = ",".join([time_fmt] + ["%d"] * len(cols))
    np.savetxt(buf, data, fmt=fmt)
    return buf.getvalue()


# ----------------------------------------------------------------------------- generator

def generate(out: Path, seed: int = SEED, table_path: Path | None = None) -> None:
    rng = np.random.default_rng(seed)
    note = SYNTHETIC_NOTE.format(seed=seed)
    table = read_table(table_path or REPO / "reference" / "muscle_forces_by_grasp.csv")
    muscles = list(table)
    ramp_t = T_RAMP

    # --- MVC trials
    mvc_rows = []
    n_mvc = int(round((MVC_REST + MVC_REPS * (2 * ramp_t + MVC_HOLD + MVC_REST)) * FS_EMG))
    t_mvc = np.arange(n_mvc) / FS_EMG
    holds = []
    t0 = MVC_REST + ramp_t
    for _ in range(MVC_REPS):
        holds.append((t0, t0 + MVC_HOLD))
        t0 += MVC_HOLD + 2 * ramp_t + MVC_REST
    p = hold_profile(t_mvc, holds, ramp_t)
    ramp_w = 4.0 * p * (1.0 - p)  # smooth bump, 1 mid-ramp
    for m in muscles:
        emg = A_MVC_UV[m] * p * shwedyk_carrier(rng, n_mvc, FS_EMG) + nuisances(rng, t_mvc, ramp_w)
        rel = f"emg/mvc_{m}.csv.gz"
        write_text(out / rel, timeseries_csv(note + f"; MVC of {m}, EMG in uV",
                                             ["time_s", m], t_mvc, [emg], "%.4f"))
        wins = " ".join(f"{a + HOLD_MARGIN:.2f}-{b - HOLD_MARGIN:.2f}" for a, b in holds)
        mvc_rows.append((m, F_MVC_N[m], rel, wins))
    lines = [f"# {note}", "# F_MVC are invented plausible values (dynamometer stand-ins)",
             "muscle,mvc_force_N,file,hold_windows_s"]
    lines += [f"{m},{f:.1f},{rel},{w}" for m, f, rel, w in mvc_rows]
    write_text(out / "mvc.csv", "\n".join(lines) + "\n")

    # --- glove calibration (gain deg/count, offset count) per sensor
    gains = {s: float(np.round(rng.uniform(0.5, 0.7), 4)) for s in SENSORS}
    zero_counts = {s: float(np.round(rng.uniform(50.0, 70.0), 1)) for s in SENSORS}
    cal = [f"# {note}", "# angle_deg(dof) = sum over rows of gain * counts(sensor); "
           "sensor 'offset' is the constant term (deg)", "dof,sensor,gain"]
    dof_terms: dict[str, list[tuple[str, float]]] = {}
    dof_offset: dict[str, float] = {}
    # invert the sensor model: each measured dof = its sensor chain (triangular by construction)
    for s, reads in SENSORS.items():
        if len(reads) == 1:
            (dof, _), = reads.items()
            dof_terms.setdefault(dof, []).append((s, gains[s]))
            dof_offset[dof] = dof_offset.get(dof, 0.0) - gains[s] * zero_counts[s]
    # little abduction = ring-little spread + ring abduction
    s_rl, s_mr = "ring_little_abduction", "middle_ring_abduction"
    dof_terms["little_mcp_abduction"] = [(s_rl, gains[s_rl]), (s_mr, gains[s_mr])]
    dof_offset["little_mcp_abduction"] = -gains[s_rl] * zero_counts[s_rl] - gains[s_mr] * \
        zero_counts[s_mr]
    for dof, terms in dof_terms.items():
        for s, g in terms:
            cal.append(f"{dof},{s},{g:.4f}")
        cal.append(f"{dof},offset,{dof_offset[dof]:.4f}")
    write_text(out / "glove" / "calibration.csv", "\n".join(cal) + "\n")

    # --- grasp trials
    toml = [f"# {note}", "# Trials per grasp, their files (paths relative to this folder) and",
            "# hold windows [start, end] in s. Formats: subjects/README.md.", "",
            "[subject]", 'id = "S01"', "synthetic = true",
            f'note = "{note}"', "",
            "[emg]", "# processing settings; defaults documented in docs/emg.md",
            "mains_hz = 50.0", "",
            "[glove]", 'format = "raw"', 'calibration = "glove/calibration.csv"', ""]
    n = int(round(T_TRIAL * FS_EMG))
    t = np.arange(n) / FS_EMG
    ng = int(round(T_TRIAL * FS_GLOVE))
    tg = np.arange(ng) / FS_GLOVE
    for grasp in GRASPS:
        forces = {m: exact_mean_values(rng, table[m][grasp], FORCE_CV, N_TRIALS, 0.001)
                  for m in muscles}
        nominal = GRASP_ANGLES_DEG[grasp]
        angles = {d: exact_mean_values(rng, v, 0.0, N_TRIALS, 0.01, abs_sd=ANGLE_SD_DEG)
                  for d, v in nominal.items()}
        toml += [f"[grasps.{grasp}]", "trials = ["]
        for k in range(N_TRIALS):
            name = f"{grasp}_{k + 1:02d}"
            onset = T_REST0 + T_RAMP + rng.uniform(-ONSET_JITTER, ONSET_JITTER)
            hold = (onset, onset + T_HOLD)
            p = hold_profile(t, [hold], ramp_t)
            ramp_w = 4.0 * p * (1.0 - p)  # smooth bump, 1 mid-ramp
            cols = []
            for m in muscles:
                a = forces[m][k] / F_MVC_N[m]
                cols.append(A_MVC_UV[m] * a * p * shwedyk_carrier(rng, n, FS_EMG)
                            + nuisances(rng, t, ramp_w))
            write_text(out / "emg" / f"{name}.csv.gz",
                       timeseries_csv(note + f"; {grasp} trial {k + 1}, EMG in uV",
                                      ["time_s", *muscles], t, cols, "%.4f"))
            truth = [f"# {note}", "# ground-truth muscle force of this trial (hold phase)",
                     "muscle,force_N"] + [f"{m},{forces[m][k]:.3f}" for m in muscles]
            write_text(out / "emg" / f"{name}.truth.csv", "\n".join(truth) + "\n")

            # glove: rest -> grasp posture (same ramps) -> rest, sensors in counts
            pg = hold_profile(tg, [hold], ramp_t)
            ang = {d: REST_ANGLES_DEG[d] + (angles[d][k] - REST_ANGLES_DEG[d]) * pg
                   for d in nominal}
            sens = []
            for s, reads in SENSORS.items():
                val = sum((c * ang[d] for d, c in reads.items()), np.zeros(ng))
                if s == "palm_arch":
                    val = 10.0 + 15.0 * pg
                counts = val / gains[s] + zero_counts[s] + rng.normal(0, SENSOR_NOISE_COUNTS, ng)
                if counts.min() < 0 or counts.max() > 255:
                    raise RuntimeError(f"sensor {s} leaves the 8-bit range")
                sens.append(counts)
            write_text(out / "glove" / f"{name}.csv.gz",
                       timeseries_csv(note + f"; {grasp} trial {k + 1}, glove counts",
                                      ["time_s", *SENSORS], tg, sens, "%.2f"))
            gt = [f"# {note}", "# ground-truth joint angles of this trial's hold posture; DOFs "
                  "the glove cannot see are at neutral", "dof,angle_deg"]
            gt += [f"{d},{angles[d][k]:.2f}" for d in nominal]
            write_text(out / "glove" / f"{name}.truth.csv", "\n".join(gt) + "\n")

            hs = (round(hold[0] + HOLD_MARGIN, 2), round(hold[1] - HOLD_MARGIN, 2))
            toml.append(f'  {{ trial = {k + 1}, emg = "emg/{name}.csv.gz", '
                        f'glove = "glove/{name}.csv.gz", hold_s = [{hs[0]:.2f}, {hs[1]:.2f}] }},')
        toml += ["]", ""]
    write_text(out / "trials.toml", "\n".join(toml))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=REPO / "subjects" / "S01",
                    help="subject folder to write (default subjects/S01)")
    ap.add_argument("--seed", type=int, default=SEED, help=f"random seed (default {SEED})")
    args = ap.parse_args()
    generate(args.out, args.seed)
    print(f"wrote synthetic subject to {args.out}")


if __name__ == "__main__":
    main()
