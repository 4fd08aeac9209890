"""Universal neural BTF (seed 002): BTF data rendered from SVBRDFs, the universal basis, per-material fits.

==========  ================================================================================
module      what
==========  ================================================================================
``svbrdf``  seeded tileable SVBRDFs of 8 families
``data``    BTFs path traced with Mitsuba from them, BTF and dataset files
``fit``     universal basis training (§4.2), per-material fitting (§4.3), NeuMIP baseline (§5.2)
==========  ================================================================================

The network maths lives in :mod:`mi_plugins.neural_basis` (the plugin runs the same weights).
Other features use only the names below.
"""

from .data import (BTFData, BTFDataError, BTFRenderSettings, load_btf, load_dataset, render_btf, render_dataset,
                   render_material, save_btf)
from .svbrdf import FAMILIES, SVBRDF, constant_svbrdf, make_svbrdf
from .fit import (OptimSettings, Prefilter, fit_file, fit_material, fit_prefilter, fit_settings, gaussian_periodic,
                  heldout_psnr, predict, psnr, psnr_pair, split_slices, train_basis, train_per_material,
                  weights_digest)

__all__ = [
    "BTFData", "BTFDataError", "BTFRenderSettings", "FAMILIES", "OptimSettings", "Prefilter", "SVBRDF",
    "constant_svbrdf", "fit_file", "fit_material", "fit_prefilter", "fit_settings", "gaussian_periodic", "heldout_psnr",
    "load_btf", "load_dataset", "make_svbrdf", "predict", "psnr", "psnr_pair", "render_btf", "render_dataset", "render_material",
    "save_btf", "split_slices", "train_basis", "train_per_material", "weights_digest",
]
