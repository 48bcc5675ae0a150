"""Longitudinal trends for clinicians: per-session summaries, statistics, attention list and exports."""
