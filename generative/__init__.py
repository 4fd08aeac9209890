"""photoreal: generative package."""
