"""An example sonarset predictor plugin (see decay.py)."""
