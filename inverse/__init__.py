"""Dr.Jit optimisation, one folder per feature: ``morph/`` (geometry), ``face/`` (UV-space face materials),
``btf/`` (universal neural BTF). Features use each other only through the foundation."""
