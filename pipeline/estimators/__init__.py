"""Knee-angle estimators over one leg, by name: the registry is the dict literal below (add an estimator here).

Each is a leaf function ``(LegInput) -> (angle_deg, diagnostics)`` (:mod:`pipeline.leg_input`): knee flexion [deg]
on the leg's grid, NaN where it has no estimate, and its frozen diagnostics. Look up with :func:`get_estimator`.
"""

from __future__ import annotations

from pipeline.estimators.cf import cf_estimator
from pipeline.estimators.ekf import ekf_leg
from pipeline.estimators.go import go_relative
from pipeline.estimators.kf import kf_leg
from pipeline.leg_input import Estimator

REGISTRY: dict[str, Estimator] = {
    "go": go_relative,  # Allseits et al. 2018: gyroscope only, one zero-angle update per stride
    "cf": cf_estimator,  # Seel et al. 2014 / Rhudy et al. 2024 Eq. 17
    "kf": kf_leg,  # Rhudy et al. 2024 Eq. 18-21
    "ekf": ekf_leg,  # Rhudy et al. 2024 Eq. 22-24
}


def get_estimator(name: str) -> Estimator:
    """The estimator registered as ``name``; ValueError naming the available ones otherwise."""
    try:
        return REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown estimator {name!r}; available: {', '.join(available())}") from None


def available() -> list[str]:
    """Names of the registered estimators, sorted."""
    return sorted(REGISTRY)
