"""Low-level ops shared by datasets, attacks, models and evaluation."""
