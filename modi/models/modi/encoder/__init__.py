"""The MoDi encoder into W+ (paper 001 §3.4, §4.2) and the ill-posed tasks it solves.

* ``model``        -- the reverse-hierarchy encoder predicting W+ (offset from the mean latent)
* ``training``     -- losses (rec, contact BCE, root, FK positions), data split, trainer, checkpoints
* ``metrics``      -- the paper's Table 5 errors and trivial baselines
* ``applications`` -- inversion, prefix completion, fusion, denoising, spatial editing (BVH + GIF side by side)
"""
