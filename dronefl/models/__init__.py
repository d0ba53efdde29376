"""The on-drone trajectory predictor: model, training windows, local training."""
