"""photoreal: photoreal package."""
