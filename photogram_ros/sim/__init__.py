"""The synthetic survey flight generator: the source of ground truth for every accuracy test."""
