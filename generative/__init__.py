"""photoreal's torch models, one folder per feature, named like the feature they serve:
``diffrender/`` (the diffusion renderer), ``btf/`` (material diffusion), ``face/`` (learned face stages),
``gan/`` (pix2pix, CycleGAN, Morph-GAN, joint training); ``diffusion/`` is the core the first three share."""
