"""Per-patient knee calibrations: a clinician's measured standing knee flexion per leg, used as the absolute zero."""
