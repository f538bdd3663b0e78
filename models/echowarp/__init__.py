"""EchoWarp: sonarset's own predictor, designed from where EchoPT's and flow's errors lie
(model.py). Trained by the same trainer as EchoPT and the reference methods (``model = "echowarp"``)."""
