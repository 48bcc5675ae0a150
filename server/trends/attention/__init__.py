"""The attention list: flags from evidence (``rules``), clinic thresholds and presets (``params``), the query
(``service``)."""

from server.trends.attention.params import PRESETS, AttentionParams, params_for
from server.trends.attention.rules import SEVERITY
from server.trends.attention.service import attention_list

__all__ = ["PRESETS", "SEVERITY", "AttentionParams", "attention_list", "params_for"]
