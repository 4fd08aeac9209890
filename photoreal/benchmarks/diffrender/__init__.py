"""`bench diffrender` (``bench``): the diffusion renderer against PBR recomposition and the GANs on held-out views,
with what it measures with (``measure``), its noise-free references and distribution metrics (``references``)
and its sweep chart (``charts``)."""
