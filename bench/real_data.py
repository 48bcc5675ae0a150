"""Loaders of the real recordings in ``../shared/data/real`` (read at runtime, never copied into the repo).

* biomechZoo S11_WT_01 (Dixon et al., Comput Methods Programs Biomed 2017): one 10 s walking trial, 100 Hz,
  Xsens on both thighs and shanks, synchronised Vicon Plug-in-Gait knee flexion.
* Tan, Wang et al., IEEE Trans. Ind. Informatics 2022 (KAM/KFM): right-leg step windows on an instrumented
  treadmill, force-plate heel strike and toe-off.

``REAL_DATA_DIR`` is ``../shared/data/real`` relative to the repository; the environment variable
``GAITMON_REAL_DATA`` overrides it. Tests and benchmarks call :func:`real_data_available` and skip otherwise.
"""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.types import RawSensorStream

REPO_DIR = Path(__file__).resolve().parent.parent
REAL_DATA_DIR = Path(os.environ.get("GAITMON_REAL_DATA", REPO_DIR.parent / "shared" / "data" / "real"))
BIOMECHZOO_CSV = Path("biomechzoo_s11_wt_01") / "S11_WT_01_imu_vicon.csv"
TAN_DIR = Path("tan_kam_kfm_steps")

_ZOO_SEGMENTS = {("right", "thigh"): "thighR", ("right", "shank"): "shankR",
                 ("left", "thigh"): "thighL", ("left", "shank"): "shankL"}
_ZOO_KNEE = {"right": "RKneeAngles_x", "left": "LKneeAngles_x"}


def real_data_available(subdir: str | Path | None = None) -> bool:
    """True when the shared real-data folder (or one of its sub-folders) exists."""
    path = REAL_DATA_DIR if subdir is None else REAL_DATA_DIR / subdir
    return path.exists()


def _read_csv_columns(path: Path) -> dict[str, np.ndarray]:
    with open(path, newline="") as fh:
        reader = csv.reader(fh)
        header = next(reader)
        rows = [row for row in reader if row]
    # Non-numeric cells (should not occur) become NaN rather than failing the whole load.
    data = np.array([[_to_float(c) for c in row] for row in rows], dtype=float)
    return {name: data[:, i] for i, name in enumerate(header)}


def _to_float(cell: str) -> float:
    try:
        return float(cell)
    except ValueError:
        return float("nan")


def load_biomechzoo(path: str | Path | None = None
                    ) -> tuple[list[RawSensorStream], dict[str, tuple[np.ndarray, np.ndarray]]]:
    """The biomechZoo trial as four raw streams (gyro rad/s, acc m/s^2) and the Vicon knee flexion per leg.

    Returns ``(streams, vicon)`` with ``vicon[leg] = (t_s, knee_flex_deg)``; flexion positive.
    """
    csv_path = Path(path) if path is not None else REAL_DATA_DIR / BIOMECHZOO_CSV
    cols = _read_csv_columns(csv_path)
    t_s = cols["time_s"]
    fs_hz = float(round(1.0 / np.median(np.diff(t_s))))
    streams = []
    for (leg, segment), seg in _ZOO_SEGMENTS.items():
        gyr = np.column_stack([cols[f"{seg}_Gyr_{a}"] for a in "XYZ"])
        acc = np.column_stack([cols[f"{seg}_Acc_{a}"] for a in "XYZ"])
        streams.append(RawSensorStream(sensor_id=seg, leg=leg, segment=segment, fs_hz=fs_hz, t_s=t_s.copy(),
                                       gyr=gyr, acc=acc, gyro_unit="rad/s", acc_unit="m/s2"))
    vicon = {leg: (t_s.copy(), cols[name].copy()) for leg, name in _ZOO_KNEE.items()}
    return streams, vicon


@dataclass(frozen=True)
class StepWindow:
    """One right-leg step window: ~20 samples before heel strike to ~20 after toe-off.

    ``hs_idx`` and ``to_idx`` are the force-plate heel strike (first stance sample) and toe-off (first
    sample after stance) indices into the window.
    """

    subject: str
    step: int
    fs_hz: float
    t_s: np.ndarray
    shank_gyr_dps: np.ndarray  # (N, 3) right shank, sensor frame
    shank_acc_mps2: np.ndarray
    thigh_gyr_dps: np.ndarray  # (N, 3) right thigh, sensor frame
    thigh_acc_mps2: np.ndarray
    hs_idx: int
    to_idx: int
    knee_flex_markers_deg: np.ndarray  # rough (about +10 deg offset): shape only


def load_tan_steps(path: str | Path | None = None) -> list[StepWindow]:
    """All step windows of all subjects in the Tan et al. folder (or of one CSV file when ``path`` is a file)."""
    base = Path(path) if path is not None else REAL_DATA_DIR / TAN_DIR
    files = [base] if base.is_file() else sorted(base.glob("subject_*_steps.csv"))
    windows: list[StepWindow] = []
    for f in files:
        subject = f.stem.replace("_steps", "")
        cols = _read_csv_columns(f)
        steps = cols["step"].astype(int)
        for step in np.unique(steps):
            sel = steps == step
            phase = cols["force_phase"][sel] > 0.5
            on = np.flatnonzero(phase)
            if on.size == 0:
                continue
            hs = int(on[0])
            off_after = np.flatnonzero(~phase[hs:])
            to = hs + int(off_after[0]) if off_after.size else int(phase.size)
            t = cols["time_s"][sel]
            dt = np.diff(t)
            fs_hz = float(round(1.0 / np.median(dt))) if dt.size and np.median(dt) > 0 else 100.0
            windows.append(StepWindow(
                subject=subject, step=int(step), fs_hz=fs_hz, t_s=np.arange(int(sel.sum())) / fs_hz,
                shank_gyr_dps=np.column_stack([cols[f"Gyro{a}_R_SHANK"][sel] for a in "XYZ"]),
                shank_acc_mps2=np.column_stack([cols[f"Accel{a}_R_SHANK"][sel] for a in "XYZ"]),
                thigh_gyr_dps=np.column_stack([cols[f"Gyro{a}_R_THIGH"][sel] for a in "XYZ"]),
                thigh_acc_mps2=np.column_stack([cols[f"Accel{a}_R_THIGH"][sel] for a in "XYZ"]),
                hs_idx=hs, to_idx=to, knee_flex_markers_deg=cols["R_knee_flex_approx_markers_deg"][sel],
            ))
    return windows
