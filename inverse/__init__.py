"""photoreal: inverse package."""
