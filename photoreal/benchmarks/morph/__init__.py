"""The morph benchmarks: `bench morph` (``bench``: cases, suite, framing, floor, iteration cost; its charts in
``charts``), `bench morph-seeds` (``seeds``: the suite over draws, two settings compared) and
`bench morph-light-draws` (``light_draws``: each light choice under other draws of its estimate)."""
