"""`photoreal bench …`: one module per benchmark (plugins, face, morph, btf, gan), each writing JSON and charts.

Every benchmark lives here, one rule for all: features stay free of heavy runs and tests stay small.
Speed is always a ratio against a reference measured in the same run.
"""
