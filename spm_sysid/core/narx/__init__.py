"""The model and its search: terms, criteria, least squares, evaluator, GA, validation."""
