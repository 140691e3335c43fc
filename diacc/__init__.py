"""diacc: dual-interaction-aware cooperative control of CAVs in highway bottlenecks."""

__version__ = "0.1.0"
