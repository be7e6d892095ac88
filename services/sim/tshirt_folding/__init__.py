"""The T-shirt-folding world: a T-shaped flex cloth on a table under a top-down camera."""
