"""Loaders for recorded data, one format per module; each streams records in file order."""
