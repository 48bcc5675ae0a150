"""Knee-angle estimators over one prepared leg, by name (open registry: ``kf``/``ekf`` add themselves here).

An estimator is a function ``(LegData) -> np.ndarray`` returning knee flexion [deg] on the leg's grid, NaN where it
has no estimate. Register with ``@register("name")``; look up with :func:`get_estimator`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from pipeline.axes import JointAxes, JointCentres
from pipeline.phases import GaitEvents
from pipeline.prepare import PreparedLeg


@dataclass
class LegData:
    """Everything an estimator may use, computed once per leg by :mod:`pipeline.session`."""

    prep: PreparedLeg
    axes: JointAxes
    centres: JointCentres | None
    rate_dps: np.ndarray  # knee flexion rate g1.j1 - g2.j2 (Seel Eq. 4 integrand), NaN where masked
    acc_angle_deg: np.ndarray  # accelerometer knee angle (Seel Eq. 6-7), NaN where masked
    shank_sag_dps: np.ndarray  # g2.j2, positive mid-swing
    events: GaitEvents
    activity: str = "walking"
    extras: dict = field(default_factory=dict)  # estimator diagnostics (JSON-serialisable)

    @property
    def fs_hz(self) -> float:
        return self.prep.fs_hz


Estimator = Callable[[LegData], np.ndarray]
_REGISTRY: dict[str, Estimator] = {}


def register(name: str) -> Callable[[Estimator], Estimator]:
    def deco(fn: Estimator) -> Estimator:
        _REGISTRY[name] = fn
        return fn
    return deco


def get_estimator(name: str) -> Estimator:
    _load_builtin()
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown estimator {name!r}; available: {', '.join(available())}") from None


def available() -> list[str]:
    _load_builtin()
    return sorted(_REGISTRY)


def _load_builtin() -> None:
    """Import every module of this package once, so each registers its estimators (``cf``, ``go``, ``kf``, ...).
    Lazy, so the submodules can import LegData/register from here without a cycle."""
    import importlib
    import pkgutil

    for mod in pkgutil.iter_modules(__path__):
        importlib.import_module(f"{__name__}.{mod.name}")
