"""Surface EMG to muscle force (brief section 2).

Chain, per muscle and trial (settings: :class:`EmgSettings`, table ``[emg]`` of ``trials.toml``):

1. baseline offset removed (median), mains hum removed by zero-phase notches at the mains frequency
   and its harmonics inside the pass band (50/60 Hz lie inside 20-400 Hz, so the band-pass alone
   cannot remove them);
2. zero-phase Butterworth band-pass (default 20-400 Hz, order 4). Forward-backward filtering
   squares the magnitude response, so the design edges are widened such that the *applied*
   (two-pass) response is -3 dB at the stated corners;
3. full-wave rectification and a linear envelope: zero-phase Butterworth low-pass (default 6 Hz,
   order 2, same -3 dB correction) or a centred moving RMS;
4. EMG level = mean of the envelope over the trial's hold window (``hold_s`` in ``trials.toml``) or
   over a detected steady hold;
5. normalisation by the same muscle's MVC level (mean envelope over the MVC hold windows of
   ``mvc.csv``) and force = (EMG / EMG_MVC) * F_MVC (N), linear for isometric contraction;
6. mean and sample SD over the grasp's trials.

A normalised level above 1 (trial EMG above the MVC envelope) warns (:class:`AboveMvcWarning`);
the ``above_mvc`` policy then keeps the unclipped force (default), clips it to F_MVC, or raises.

Units: time s, frequency Hz, force N. EMG may be in any unit (we write uV) as long as a muscle's
trial and MVC files use the same one: it cancels in the normalisation. Data layout and file
formats: ``subjects/README.md``; method notes: ``docs/emg.md``.
"""

from __future__ import annotations

import csv
import gzip
import io
import math
import warnings
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from handfe.config import bounds, choices, from_dict, load_toml
from handfe.errors import ConfigError, InputError

MUSCLES = ("FDS", "FDP", "APL", "APB", "AP", "FPB", "FDI", "SDI", "TDI")
GRASPS = ("cylindrical", "spherical", "precision")
TIME_COLUMN = "time_s"


class EmgWarning(UserWarning):
    """Something in the EMG data the user should look at (the result is still computed)."""


class AboveMvcWarning(EmgWarning):
    """A trial's normalised EMG exceeds 1 (above the muscle's MVC envelope)."""


# ----------------------------------------------------------------------------- settings

@dataclass(frozen=True)
class EmgSettings:
    """EMG processing settings (table ``[emg]`` of a subject's ``trials.toml``)."""

    bandpass_hz: tuple[float, float] = (20.0, 400.0)
    bandpass_order: int = field(default=4, metadata=bounds(1, 8))
    mains_hz: float = field(default=50.0, metadata=bounds(0.0))  # 0 = no hum removal
    mains_method: str = field(default="fit", metadata=choices("fit", "notch"))
    mains_search_hz: float = field(default=0.5, metadata=bounds(0.0, 5.0))
    notch_q: float = field(default=30.0, metadata=bounds(1.0, 500.0))
    envelope: str = field(default="lowpass", metadata=choices("lowpass", "rms"))
    envelope_lowpass_hz: float = field(default=6.0, metadata=bounds(0.1, 50.0))
    envelope_order: int = field(default=2, metadata=bounds(1, 8))
    rms_window_s: float = field(default=0.25, metadata=bounds(0.01, 5.0))
    hold: str = field(default="window", metadata=choices("window", "detect"))
    detect_trim_s: float = field(default=0.5, metadata=bounds(0.0, 5.0))
    min_hold_s: float = field(default=1.0, metadata=bounds(0.1, 60.0))
    mvc_statistic: str = field(default="mean", metadata=choices("mean", "max"))
    above_mvc: str = field(default="warn", metadata=choices("warn", "clip", "error"))
    max_gap_s: float = field(default=0.0, metadata=bounds(0.0, 1.0))

    def __post_init__(self) -> None:
        lo, hi = self.bandpass_hz
        if not 0.0 < lo < hi:
            raise ValueError(f"bandpass_hz = [{lo:g}, {hi:g}]: need 0 < low < high")

    def describe(self) -> str:
        lo, hi = self.bandpass_hz
        env = (f"low-pass {self.envelope_lowpass_hz:g} Hz envelope" if self.envelope == "lowpass"
               else f"moving-RMS envelope {self.rms_window_s * 1e3:g} ms")
        mains = (f"mains {self.mains_hz:g} Hz + harmonics removed ({self.mains_method})"
                 if self.mains_hz > 0 else "no mains-hum removal")
        hold = "hold windows from trials.toml" if self.hold == "window" else "detected holds"
        return (f"band-pass {lo:g}-{hi:g} Hz Butterworth order {self.bandpass_order} zero-phase, "
                f"{mains}, {env}, {hold}")


@dataclass(frozen=True)
class TrialSpec:
    """One trial of a grasp in ``trials.toml``; paths relative to the subject folder."""

    trial: int = field(metadata=bounds(1))
    emg: str = ""
    glove: str = ""
    hold_s: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.hold_s is not None and not self.hold_s[0] < self.hold_s[1]:
            raise ValueError(f"trial {self.trial}: hold_s = {list(self.hold_s)}: start >= end")


@dataclass(frozen=True)
class GraspSpec:
    trials: tuple[TrialSpec, ...]


@dataclass(frozen=True)
class SubjectInfo:
    id: str = ""
    synthetic: bool = False
    note: str = ""


@dataclass(frozen=True)
class _TrialsFile:
    grasps: dict[str, GraspSpec]
    subject: SubjectInfo = field(default_factory=SubjectInfo)
    emg: dict[str, Any] = field(default_factory=dict)
    glove: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Subject:
    """A subject folder as described by its ``trials.toml``."""

    dir: Path
    id: str
    synthetic: bool
    note: str
    grasps: dict[str, tuple[TrialSpec, ...]]
    emg_table: dict[str, Any]
    glove_table: dict[str, Any]

    @property
    def trials_file(self) -> Path:
        return self.dir / "trials.toml"

    def trials(self, grasp: str, trial: int | None = None) -> tuple[TrialSpec, ...]:
        """The grasp's trials (or just trial number ``trial``)."""
        if grasp not in self.grasps:
            raise InputError(f"{self.trials_file}: no grasp '{grasp}' (listed: "
                             f"{', '.join(self.grasps) or 'none'})")
        specs = self.grasps[grasp]
        if trial is None:
            return specs
        sel = tuple(s for s in specs if s.trial == trial)
        if not sel:
            raise InputError(f"{self.trials_file}: grasp '{grasp}' has no trial {trial} "
                             f"(trials: {', '.join(str(s.trial) for s in specs)})")
        return sel

    def path(self, rel: str) -> Path:
        p = Path(rel)
        return p if p.is_absolute() else self.dir / p

    def emg_settings(self, **overrides: Any) -> EmgSettings:
        """The subject's ``[emg]`` settings with ``overrides`` (None values ignored) applied."""
        data = dict(self.emg_table)
        data.update({k: v for k, v in overrides.items() if v is not None})
        return from_dict(EmgSettings, data, source=str(self.trials_file), prefix="emg.")


def read_subject(subject_dir: str | Path) -> Subject:
    """Read ``<subject_dir>/trials.toml`` (errors name the file and the key)."""
    d = Path(subject_dir)
    if not d.is_dir():
        raise InputError(f"{d}: subject folder not found")
    path = d / "trials.toml"
    spec = from_dict(_TrialsFile, load_toml(path), source=str(path))
    grasps = {}
    for name, g in spec.grasps.items():
        nums = [t.trial for t in g.trials]
        if not nums:
            raise ConfigError(f"{path}: grasps.{name}.trials is empty")
        if len(set(nums)) != len(nums):
            raise ConfigError(f"{path}: grasps.{name}: duplicate trial numbers {nums}")
        grasps[name] = tuple(g.trials)
    return Subject(d, spec.subject.id or d.name, spec.subject.synthetic, spec.subject.note,
                   grasps, dict(spec.emg), dict(spec.glove))


# ----------------------------------------------------------------------------- CSV time series

@dataclass(frozen=True)
class TimeSeries:
    """A uniformly sampled recording: ``time`` (s) and named channels."""

    path: Path
    time: np.ndarray
    columns: dict[str, np.ndarray]

    @property
    def fs(self) -> float:
        """Sampling rate (Hz) from the mean sample interval (the grid is checked uniform)."""
        return (self.time.size - 1) / float(self.time[-1] - self.time[0])

    def column(self, name: str, what: str = "column") -> np.ndarray:
        if name not in self.columns:
            raise InputError(f"{self.path}: {what} '{name}' missing (columns: "
                             f"{', '.join(self.columns)})")
        return self.columns[name]


def _open_text(path: Path) -> str:
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    if path.suffix == ".gz":
        with gzip.open(path, "rt") as fh:
            return fh.read()
    return path.read_text()


def _parse_slow(path: Path, body: list[str], first_line: int, ncol: int,
                header: list[str]) -> np.ndarray:
    """Tolerant parser: empty cells and 'nan' become NaN; anything else non-numeric is an error."""
    out = np.full((len(body), ncol), np.nan)
    for i, row in enumerate(csv.reader(body)):
        if len(row) != ncol:
            raise InputError(f"{path}, line {first_line + i}: {len(row)} values, expected {ncol} "
                             f"({', '.join(header)})")
        for j, cell in enumerate(row):
            cell = cell.strip()
            if cell == "" or cell.lower() == "nan":
                continue
            try:
                out[i, j] = float(cell)
            except ValueError:
                raise InputError(f"{path}, line {first_line + i}, column '{header[j]}': "
                                 f"'{cell}' is not a number") from None
    return out


def _fill_gaps(path: Path, name: str, t: np.ndarray, x: np.ndarray, max_gap_s: float) -> None:
    """Interpolate (in place) NaN runs no longer than ``max_gap_s`` inside the record, else
    raise an error naming the file, column and time."""
    bad = np.isnan(x)
    if not bad.any():
        return
    idx = np.flatnonzero(bad)
    starts = idx[np.r_[True, np.diff(idx) > 1]]
    ends = idx[np.r_[np.diff(idx) > 1, True]]
    dt = float(np.median(np.diff(t)))
    for a, b in zip(starts, ends, strict=True):
        dur = (b - a + 1) * dt
        if a == 0 or b == x.size - 1 or dur > max_gap_s + 1e-12:
            extra = (f"; gaps up to max_gap_s = {max_gap_s:g} s are interpolated"
                     if max_gap_s > 0 else "; set emg.max_gap_s to interpolate short gaps")
            raise InputError(f"{path}: column '{name}' has {b - a + 1} missing/NaN value(s) "
                             f"from t = {t[a]:.4f} s to {t[b]:.4f} s{extra}")
    good = ~bad
    x[bad] = np.interp(t[bad], t[good], x[good])
    warnings.warn(f"{path}: column '{name}': interpolated {idx.size} missing value(s) "
                  f"(first at t = {t[idx[0]]:.4f} s)", EmgWarning, stacklevel=3)


@lru_cache(maxsize=64)
def _read_cached(path: str, mtime_ns: int, size: int, max_gap_s: float) -> TimeSeries:
    p = Path(path)
    lines = _open_text(p).splitlines()
    k = 0
    while k < len(lines) and (lines[k].startswith("#") or not lines[k].strip()):
        k += 1
    if k == len(lines):
        raise InputError(f"{p}: no header line")
    header = [h.strip() for h in lines[k].split(",")]
    if header[0] != TIME_COLUMN:
        raise InputError(f"{p}: first column must be '{TIME_COLUMN}', got '{header[0]}'")
    dup = {h for h in header if header.count(h) > 1}
    if dup:
        raise InputError(f"{p}: duplicate column '{sorted(dup)[0]}'")
    body = [ln for ln in lines[k + 1:] if ln.strip() and not ln.startswith("#")]
    if len(body) < 2:
        raise InputError(f"{p}: fewer than two samples")
    try:
        data = np.loadtxt(io.StringIO("\n".join(body)), delimiter=",", ndmin=2, dtype=float)
        if data.shape[1] != len(header):
            raise ValueError
    except ValueError:
        data = _parse_slow(p, body, k + 2, len(header), header)
    t = data[:, 0]
    if np.isnan(t).any():
        i = int(np.flatnonzero(np.isnan(t))[0])
        raise InputError(f"{p}: column '{TIME_COLUMN}' is missing at data row {i + 1}")
    dt = np.diff(t)
    if (dt <= 0).any():
        i = int(np.flatnonzero(dt <= 0)[0])
        raise InputError(f"{p}: {TIME_COLUMN} does not increase at t = {t[i]:.4f} s "
                         f"-> {t[i + 1]:.4f} s")
    med = float(np.median(dt))
    if (dt > 1.5 * med).any():
        i = int(np.flatnonzero(dt > 1.5 * med)[0])
        raise InputError(f"{p}: gap in the recording ({TIME_COLUMN}): samples missing between "
                         f"t = {t[i]:.4f} s and {t[i + 1]:.4f} s (sampling interval "
                         f"{med * 1e3:.3g} ms); all channels must be uniformly sampled")
    cols = {}
    for j, name in enumerate(header[1:], start=1):
        x = data[:, j].copy()
        _fill_gaps(p, name, t, x, max_gap_s)
        x.flags.writeable = False
        cols[name] = x
    t.flags.writeable = False
    return TimeSeries(p, t, cols)


def read_timeseries(path: str | Path, *, max_gap_s: float = 0.0) -> TimeSeries:
    """Read a CSV (or .csv.gz) time series: ``#`` comment lines, a header whose first column is
    ``time_s``, then uniformly sampled rows. NaN/empty cells raise an error naming the file,
    column and time unless the run is at most ``max_gap_s`` long (then linearly interpolated,
    with a warning). Results are cached per file version; arrays are read-only."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: file not found")
    st = p.stat()
    return _read_cached(str(p.resolve()), st.st_mtime_ns, st.st_size, float(max_gap_s))


# ----------------------------------------------------------------------------- filters

_ZP = math.sqrt(2.0) - 1.0  # |H|^2 of one pass at the corner so that two passes give -3 dB


def _warp(f: float, fs: float) -> float:
    return 2.0 * fs * math.tan(math.pi * f / fs)


def _unwarp(w: float, fs: float) -> float:
    return fs / math.pi * math.atan(w / (2.0 * fs))


def check_sampling_rate(fs: float, band_hz: tuple[float, float], source: str = "") -> None:
    """Raise :class:`InputError` if ``fs`` (Hz) cannot carry the band-pass band."""
    hi = band_hz[1]
    where = f"{source}: " if source else ""
    if fs <= 2.0 * hi:
        raise InputError(f"{where}sampling rate {fs:.5g} Hz is too low for the {hi:g} Hz upper "
                         f"band-pass corner: the Nyquist frequency fs/2 = {fs / 2:g} Hz must "
                         f"exceed it (record at > {2 * hi:g} Hz, about 2 kHz is usual, or lower "
                         f"emg.bandpass_hz)")


def bandpass_sos(fs: float, band_hz: tuple[float, float] = (20.0, 400.0), order: int = 4,
                 source: str = "") -> np.ndarray:
    """Second-order sections of the Butterworth band-pass whose *zero-phase* (forward-backward)
    response is -3 dB at ``band_hz``. ``order`` is the low-pass prototype order (2*order poles).

    The prototype satisfies |H|^2 = 1/(1 + W^(2n)); two passes give 1/(1 + W^(2n))^2, which is
    1/2 at W_c = (sqrt(2) - 1)^(1/(2n)). With the band-pass map W = (w^2 - w0^2)/(w B) and
    pre-warped corners, keeping w0^2 = w1 w2 and setting B = (w2 - w1)/W_c puts the two-pass
    -3 dB points exactly on the requested corners."""
    from scipy import signal

    check_sampling_rate(fs, band_hz, source)
    f1, f2 = band_hz
    w1, w2 = _warp(f1, fs), _warp(f2, fs)
    wc = _ZP ** (1.0 / (2 * order))
    w0sq = w1 * w2
    bw = (w2 - w1) / wc
    wu = 0.5 * (bw + math.sqrt(bw * bw + 4.0 * w0sq))
    wl = w0sq / wu
    fl, fu = _unwarp(wl, fs), _unwarp(wu, fs)
    if fu >= 0.995 * fs / 2:
        raise InputError(f"{source + ': ' if source else ''}sampling rate {fs:g} Hz is too low "
                         f"for a zero-phase {f1:g}-{f2:g} Hz band-pass of order {order}: its "
                         f"design edge ({fu:.0f} Hz) reaches the Nyquist frequency {fs / 2:g} Hz")
    return signal.butter(order, [fl, fu], btype="bandpass", fs=fs, output="sos")


def lowpass_sos(fs: float, f_hz: float, order: int) -> np.ndarray:
    """Butterworth low-pass whose zero-phase response is -3 dB at ``f_hz``."""
    from scipy import signal

    fc = _unwarp(_warp(f_hz, fs) / _ZP ** (1.0 / (2 * order)), fs)
    return signal.butter(order, fc, btype="lowpass", fs=fs, output="sos")


def notch_sos(fs: float, mains_hz: float, q: float, f_max: float) -> np.ndarray | None:
    """Cascade of IIR notches at ``mains_hz`` and its harmonics up to ``f_max`` (Hz)."""
    from scipy import signal

    if mains_hz <= 0:
        return None
    secs = []
    k = 1
    while k * mains_hz <= f_max and k * mains_hz < 0.98 * fs / 2:
        b, a = signal.iirnotch(k * mains_hz, q, fs=fs)
        secs.append(signal.tf2sos(b, a))
        k += 1
    return np.vstack(secs) if secs else None


def _zero_phase(sos: np.ndarray, x: np.ndarray, fs: float) -> np.ndarray:
    from scipy import signal

    padlen = min(x.size - 1, int(round(0.5 * fs)))
    return signal.sosfiltfilt(sos, x, padlen=padlen)


def mains_frequency(y: np.ndarray, fs: float, mains_hz: float, search_hz: float = 0.5) -> float:
    """The hum's actual fundamental (Hz) within ``mains_hz +- search_hz``: the frequency that
    maximises the Hann-windowed DTFT magnitude (0.05 Hz grid, refined to 0.0001 Hz). The DTFT
    is evaluated on the signal demodulated by ``mains_hz`` and averaged in 10 ms blocks (exact
    nulls at the other harmonics), which is cheap and accurate for offsets << 100 Hz."""
    if search_hz <= 0:
        return mains_hz
    n = y.size
    t = np.arange(n) / fs
    z = y * np.hanning(n) * np.exp(-2j * np.pi * mains_hz * t)
    m = max(1, int(round(fs / 100.0)))
    nb = n // m
    zb = z[:nb * m].reshape(nb, m).mean(axis=1)
    tb = t[:nb * m].reshape(nb, m).mean(axis=1)

    def best(offsets: np.ndarray) -> float:
        mag = np.abs(np.exp(-2j * np.pi * np.outer(offsets, tb)) @ zb)
        return float(offsets[int(np.argmax(mag))])

    d = best(np.arange(-search_hz, search_hz + 1e-9, 0.05))
    d = best(np.arange(d - 0.05, d + 0.05 + 1e-9, 0.002))
    d = best(np.arange(d - 0.002, d + 0.002 + 1e-9, 0.0001))
    return mains_hz + d


def remove_mains_fit(y: np.ndarray, fs: float, mains_hz: float, f_max: float,
                     search_hz: float = 0.5) -> np.ndarray:
    """Subtract the least-squares fit of sinusoids at the (refined) mains frequency and its
    harmonics up to ``f_max`` - a "DFT filter" as in FieldTrip's ``ft_preproc_dftfilter``. It
    removes a stationary hum completely and only 2 degrees of freedom of EMG per harmonic, so the
    EMG spectrum (and its amplitude) is left intact, unlike a notch."""
    f1 = mains_frequency(y, fs, mains_hz, search_hz)
    nh = int(min(f_max, 0.98 * fs / 2) // f1)
    if nh < 1:
        return y
    t = np.arange(y.size) / fs
    arg = 2.0 * np.pi * f1 * np.outer(t, np.arange(1, nh + 1))
    basis = np.hstack([np.cos(arg), np.sin(arg)])
    coef, *_ = np.linalg.lstsq(basis, y, rcond=None)
    return y - basis @ coef


def filter_emg(x: np.ndarray, fs: float, settings: EmgSettings, source: str = "") -> np.ndarray:
    """Offset removal, mains-hum removal and zero-phase band-pass of one raw channel. The hum fit
    runs on the raw signal (where the hum is a clean stationary sinusoid), the notch after the
    band-pass."""
    y = np.asarray(x, dtype=float) - float(np.median(x))
    f_max = settings.bandpass_hz[1]
    hum = settings.mains_hz > 0
    if hum and settings.mains_method == "fit":
        y = remove_mains_fit(y, fs, settings.mains_hz, f_max, settings.mains_search_hz)
    sos = bandpass_sos(fs, settings.bandpass_hz, settings.bandpass_order, source)
    y = _zero_phase(sos, y, fs)
    if hum and settings.mains_method == "notch":
        notch = notch_sos(fs, settings.mains_hz, settings.notch_q, f_max)
        if notch is not None:
            y = _zero_phase(notch, y, fs)
    return y


def envelope(filtered: np.ndarray, fs: float, settings: EmgSettings) -> np.ndarray:
    """Linear envelope of a band-passed channel: rectify + zero-phase low-pass, or moving RMS."""
    if settings.envelope == "lowpass":
        env = _zero_phase(lowpass_sos(fs, settings.envelope_lowpass_hz, settings.envelope_order),
                          np.abs(filtered), fs)
        return np.maximum(env, 0.0)
    n = max(1, int(round(settings.rms_window_s * fs)))
    c = np.concatenate(([0.0], np.cumsum(filtered.astype(float) ** 2)))
    i = np.arange(filtered.size)
    lo = np.clip(i - n // 2, 0, filtered.size)
    hi = np.clip(i - n // 2 + n, 0, filtered.size)
    return np.sqrt(np.maximum((c[hi] - c[lo]) / (hi - lo), 0.0))


def detect_holds(activity: np.ndarray, fs: float, *, trim_s: float = 0.5,
                 min_hold_s: float = 1.0, level: float = 0.5) -> list[tuple[float, float]]:
    """Steady holds in an activity profile (e.g. a sum of normalised envelopes): the runs above
    ``level`` times its 95th percentile, each shortened by ``trim_s`` at both ends; runs shorter
    than ``min_hold_s`` after trimming are dropped. Times in s from the first sample."""
    ref = float(np.percentile(activity, 95))
    if ref <= 0:
        return []
    above = activity >= level * ref
    edges = np.flatnonzero(np.diff(np.r_[0, above.astype(int), 0]))
    holds = []
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        t0, t1 = a / fs + trim_s, (b - 1) / fs - trim_s
        if t1 - t0 >= min_hold_s:
            holds.append((t0, t1))
    return holds


# ----------------------------------------------------------------------------- MVC and trials

@dataclass(frozen=True)
class MvcEntry:
    muscle: str
    force_N: float
    file: Path
    windows_s: tuple[tuple[float, float], ...]  # empty: detect


def read_mvc_table(subject: Subject) -> dict[str, MvcEntry]:
    """``mvc.csv``: muscle, mvc_force_N, file, hold_windows_s ("a-b c-d ...", empty = detect)."""
    path = subject.dir / "mvc.csv"
    text = _open_text(path)
    rows = list(csv.DictReader(ln for ln in text.splitlines() if ln.strip()
                               and not ln.startswith("#")))
    need = {"muscle", "mvc_force_N", "file"}
    if not rows or not need <= set(rows[0]):
        raise InputError(f"{path}: needs columns {', '.join(sorted(need))} "
                         "(and optionally hold_windows_s)")
    out = {}
    for r in rows:
        m = r["muscle"].strip()
        try:
            f = float(r["mvc_force_N"])
        except ValueError:
            raise InputError(f"{path}: {m}: mvc_force_N = '{r['mvc_force_N']}' is not a "
                             "number") from None
        if not f > 0:
            raise InputError(f"{path}: {m}: mvc_force_N = {f:g} must be > 0")
        wins = []
        for tok in (r.get("hold_windows_s") or "").split():
            try:
                a, b = (float(v) for v in tok.split("-"))
            except ValueError:
                raise InputError(f"{path}: {m}: hold window '{tok}' is not 'start-end' in "
                                 "s") from None
            if not a < b:
                raise InputError(f"{path}: {m}: hold window '{tok}' has start >= end")
            wins.append((a, b))
        out[m] = MvcEntry(m, f, subject.path(r["file"].strip()), tuple(wins))
    return out


def _window_mean(path: Path, t: np.ndarray, env: np.ndarray, win: tuple[float, float]) -> float:
    sel = (t >= win[0]) & (t <= win[1])
    if sel.sum() < 2:
        raise InputError(f"{path}: hold window {win[0]:g}-{win[1]:g} s lies outside the "
                         f"recording ({t[0]:g}-{t[-1]:g} s)")
    return float(np.mean(env[sel]))


@dataclass(frozen=True)
class ChannelTrace:
    """Raw, filtered and envelope signal of one channel (for plots and inspection)."""

    time: np.ndarray
    raw: np.ndarray
    filtered: np.ndarray
    envelope: np.ndarray


def _envelopes(ts: TimeSeries, muscles: tuple[str, ...], settings: EmgSettings,
               what: str = "muscle") -> dict[str, ChannelTrace]:
    fs = ts.fs
    check_sampling_rate(fs, settings.bandpass_hz, str(ts.path))
    out = {}
    for m in muscles:
        raw = ts.column(m, what)
        filt = filter_emg(raw, fs, settings, str(ts.path))
        out[m] = ChannelTrace(ts.time, raw, filt, envelope(filt, fs, settings))
    return out


def mvc_levels(subject: Subject, settings: EmgSettings,
               muscles: tuple[str, ...] = MUSCLES) -> dict[str, float]:
    """EMG_MVC per muscle: mean (or max over windows, ``mvc_statistic``) of the envelope of its
    MVC file over the windows of ``mvc.csv`` (detected when empty or ``hold = "detect"``)."""
    table = read_mvc_table(subject)
    out = {}
    for m in muscles:
        if m not in table:
            raise InputError(f"{subject.dir / 'mvc.csv'}: muscle '{m}' missing")
        e = table[m]
        ts = read_timeseries(e.file, max_gap_s=settings.max_gap_s)
        tr = _envelopes(ts, (m,), settings)[m]
        wins = list(e.windows_s)
        if settings.hold == "detect" or not wins:
            wins = detect_holds(tr.envelope, ts.fs, trim_s=settings.detect_trim_s,
                                min_hold_s=settings.min_hold_s)
            wins = [(ts.time[0] + a, ts.time[0] + b) for a, b in wins]
            if not wins:
                raise InputError(f"{e.file}: no steady MVC hold of >= {settings.min_hold_s:g} s "
                                 f"found in '{m}'; give hold_windows_s in mvc.csv")
        levels = [_window_mean(e.file, tr.time, tr.envelope, w) for w in wins]
        lev = float(np.mean(levels)) if settings.mvc_statistic == "mean" else float(max(levels))
        if not lev > 0:
            raise InputError(f"{e.file}: MVC envelope of '{m}' is zero")
        out[m] = lev
    return out


@dataclass(frozen=True)
class TrialEmg:
    """One trial's result: EMG level (file units), normalised level (EMG/EMG_MVC) and force (N)."""

    trial: int
    file: Path
    hold_s: tuple[float, float]
    level: dict[str, float]
    normalised: dict[str, float]
    force_N: dict[str, float]


def trial_hold_window(subject: Subject, spec: TrialSpec, settings: EmgSettings,
                      traces: dict[str, ChannelTrace] | None = None) -> tuple[float, float]:
    """The trial's hold window (s): ``hold_s`` from ``trials.toml``, or the longest steady hold
    detected in the sum of the muscles' envelopes (each scaled by its 99th percentile)."""
    if settings.hold == "window" and spec.hold_s is not None:
        return spec.hold_s
    if not spec.emg:
        raise InputError(f"{subject.trials_file}: trial {spec.trial} has no hold_s and no EMG "
                         "file to detect a hold in")
    path = subject.path(spec.emg)
    if traces is None:
        ts = read_timeseries(path, max_gap_s=settings.max_gap_s)
        muscles = tuple(m for m in MUSCLES if m in ts.columns) or tuple(ts.columns)
        traces = _envelopes(ts, muscles, settings)
    t = next(iter(traces.values())).time
    act = np.zeros_like(t)
    for tr in traces.values():
        s = float(np.percentile(tr.envelope, 99))
        if s > 0:
            act += tr.envelope / s
    fs = 1.0 / float(np.median(np.diff(t)))
    holds = detect_holds(act, fs, trim_s=settings.detect_trim_s, min_hold_s=settings.min_hold_s)
    if not holds:
        raise InputError(f"{path}: no steady hold of >= {settings.min_hold_s:g} s detected; "
                         "give hold_s for this trial in trials.toml")
    a, b = max(holds, key=lambda h: h[1] - h[0])
    return (round(float(t[0] + a), 4), round(float(t[0] + b), 4))


def process_trial(subject: Subject, spec: TrialSpec, settings: EmgSettings,
                  mvc: dict[str, float], mvc_force: dict[str, float],
                  muscles: tuple[str, ...] = MUSCLES,
                  keep_traces: bool = False) -> tuple[TrialEmg, dict[str, ChannelTrace]]:
    """Forces (N) of one trial from its EMG file; see the module docstring for the chain."""
    if not spec.emg:
        raise InputError(f"{subject.trials_file}: trial {spec.trial} has no 'emg' file")
    path = subject.path(spec.emg)
    ts = read_timeseries(path, max_gap_s=settings.max_gap_s)
    traces = _envelopes(ts, muscles, settings)
    hold = trial_hold_window(subject, spec, settings, traces)
    level, norm, force = {}, {}, {}
    for m in muscles:
        lev = _window_mean(path, ts.time, traces[m].envelope, hold)
        r = lev / mvc[m]
        if r > 1.0:
            msg = (f"{path}: {m} EMG over the hold ({hold[0]:g}-{hold[1]:g} s) is {100 * r:.0f} % "
                   f"of its MVC envelope")
            if settings.above_mvc == "error":
                raise InputError(msg + " (emg.above_mvc = 'error'); check the MVC trial")
            if settings.above_mvc == "clip":
                warnings.warn(msg + f"; clipped to 100 % (force = F_MVC = {mvc_force[m]:g} N)",
                              AboveMvcWarning, stacklevel=2)
                r = 1.0
            else:
                warnings.warn(msg + f"; kept unclipped (force {r * mvc_force[m]:.1f} N > F_MVC "
                              f"{mvc_force[m]:g} N): the MVC was probably not maximal",
                              AboveMvcWarning, stacklevel=2)
        level[m], norm[m], force[m] = lev, r, r * mvc_force[m]
    return (TrialEmg(spec.trial, path, hold, level, norm, force),
            traces if keep_traces else {})


@dataclass(frozen=True)
class GraspEmg:
    """All trials of one grasp: per-trial results, MVC levels and the mean/SD forces (N)."""

    subject: Subject
    grasp: str
    settings: EmgSettings
    muscles: tuple[str, ...]
    mvc_level: dict[str, float]
    mvc_force_N: dict[str, float]
    trials: tuple[TrialEmg, ...]

    def forces(self) -> dict[str, tuple[float, float]]:
        """muscle -> (mean_N, sd_N) over the trials (sample SD; 0 for a single trial)."""
        out = {}
        for m in self.muscles:
            f = np.array([t.force_N[m] for t in self.trials])
            sd = float(np.std(f, ddof=1)) if f.size > 1 else 0.0
            out[m] = (float(np.mean(f)), sd)
        return out

    def normalised(self) -> dict[str, float]:
        """muscle -> mean normalised EMG (fraction of MVC)."""
        return {m: float(np.mean([t.normalised[m] for t in self.trials])) for m in self.muscles}


def process_grasp(subject_dir: str | Path, grasp: str, *, trial: int | None = None,
                  settings: EmgSettings | None = None,
                  muscles: tuple[str, ...] = MUSCLES) -> GraspEmg:
    """Run the EMG chain over a grasp's trials (or one trial) of a subject folder."""
    subject = read_subject(subject_dir)
    specs = subject.trials(grasp, trial)
    settings = settings or subject.emg_settings()
    table = read_mvc_table(subject)
    for m in muscles:
        if m not in table:
            raise InputError(f"{subject.dir / 'mvc.csv'}: muscle '{m}' missing")
    mvc = mvc_levels(subject, settings, muscles)
    mvc_force = {m: table[m].force_N for m in muscles}
    results = tuple(process_trial(subject, s, settings, mvc, mvc_force, muscles)[0]
                    for s in specs)
    return GraspEmg(subject, grasp, settings, muscles, mvc, mvc_force, results)


def muscle_forces(subject_dir: Path, grasp: str, *,
                  trial: int | None = None) -> dict[str, tuple[float, float]]:
    """Muscle -> (mean_N, sd_N) over the grasp's trials, or that trial's force with SD 0.

    Uses the subject's ``[emg]`` settings from ``trials.toml``. Forces in N."""
    return process_grasp(subject_dir, grasp, trial=trial).forces()
