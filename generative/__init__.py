"""photoreal's torch models, one folder per family: ``gan/`` (pix2pix, CycleGAN, Morph-GAN, joint training)."""
