"""sonarset.models: predictors, training and evaluation (torch is imported only by the learned models).

``Predictor`` is the protocol every predictor answers and ``BasePredictor`` a base class with its
optional members' defaults (models/predictor.py); importing them loads no torch.
"""

from sonarset.models.predictor import BasePredictor, Predictor

__all__ = ["BasePredictor", "Predictor"]
