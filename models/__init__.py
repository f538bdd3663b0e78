"""sonarset.models: predictors, training and evaluation (imports torch)."""
