"""The closed vocabularies of the service: session status, token role, activity, leg, segment, sensor units."""

from __future__ import annotations

from enum import StrEnum


class SessionStatus(StrEnum):
    """Life cycle of a session: receiving -> queued -> processing -> done | failed."""

    receiving = "receiving"
    queued = "queued"
    processing = "processing"
    done = "done"
    failed = "failed"


class Role(StrEnum):
    """What a bearer token may do."""

    admin = "admin"
    clinician = "clinician"
    device = "device"


class Activity(StrEnum):
    """The activity a session was recorded as (``unknown`` lets the pipeline decide)."""

    walking = "walking"
    running = "running"
    unknown = "unknown"


class StrideActivity(StrEnum):
    """The activity a stride was processed as; trends never pool the two."""

    walking = "walking"
    running = "running"

    @classmethod
    def of_session(cls, activity: str | None) -> StrideActivity:
        """The stride activity a session's activity implies when nothing better is known."""
        return cls.running if activity == Activity.running else cls.walking


class Leg(StrEnum):
    """Which leg a sensor is worn on."""

    left = "left"
    right = "right"


class Segment(StrEnum):
    """Which body segment a sensor is worn on."""

    thigh = "thigh"
    shank = "shank"


class GyroUnit(StrEnum):
    """Declared unit of the gyroscope samples."""

    deg_s = "deg/s"
    rad_s = "rad/s"


class AccUnit(StrEnum):
    """Declared unit of the accelerometer samples."""

    m_s2 = "m/s2"
    g = "g"


class CalibrationMethod(StrEnum):
    """How a standing knee flexion calibration was measured."""

    goniometer = "goniometer"
    guided_trial = "guided_trial"
