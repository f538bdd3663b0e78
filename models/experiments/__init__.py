"""The EchoPT paper's robot experiments: wheel-slip detection and corridor control through noise
bursts (``sonarset experiment slip|control``)."""
