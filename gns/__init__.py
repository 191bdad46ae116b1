"""Graph network simulator: dataset, model, training, rollout, the oracle."""
