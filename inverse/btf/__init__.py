"""Universal neural BTF (seed 002): BTF data rendered from SVBRDFs, the universal basis, per-material fits.

==========  ================================================================================
module      what
==========  ================================================================================
``svbrdf``  seeded tileable SVBRDFs of 8 families
``data``    BTFs path traced with Mitsuba from them, BTF and dataset files
``fit``     universal basis training (§4.2), per-material fitting (§4.3), NeuMIP baseline (§5.2)
``export``  a material outside photoreal: XML snippet, preview, a GGX SVBRDF distilled from it as glTF
==========  ================================================================================

The network maths lives in :mod:`mi_plugins.neural_basis` (the plugin runs the same weights).
Other features use only the names below.
"""

from .data import (BTFData, BTFDataError, BTFRenderSettings, load_btf, load_dataset, render_btf, render_dataset,
                   render_material, save_btf)
from .export import DistilSettings, MaterialExport, distil_ggx, export_material, is_neural_material
from .svbrdf import FAMILIES, SVBRDF, constant_svbrdf, make_svbrdf
from .fit import (OptimSettings, Prefilter, fit_file, fit_material, fit_prefilter, fit_settings, gaussian_periodic,
                  heldout_psnr, predict, psnr, psnr_pair, split_slices, train_basis, train_per_material,
                  weights_digest)

__all__ = [
    "DistilSettings", "MaterialExport", "distil_ggx", "export_material", "is_neural_material",
    "BTFData", "BTFDataError", "BTFRenderSettings", "FAMILIES", "OptimSettings", "Prefilter", "SVBRDF",
    "constant_svbrdf", "fit_file", "fit_material", "fit_prefilter", "fit_settings", "gaussian_periodic", "heldout_psnr",
    "load_btf", "load_dataset", "make_svbrdf", "predict", "psnr", "psnr_pair", "render_btf", "render_dataset", "render_material",
    "save_btf", "split_slices", "train_basis", "train_per_material", "weights_digest",
]
