"""MoDi's latent space applications (papers 000 §4 and 001 §4.1) on a trained generator.

* ``space``      -- seeds, the mean latent, truncation and interpolation in W and W+, shared I/O helpers
* ``clustering`` -- K-means on W, t-SNE map, cluster members side by side
* ``editing``    -- attribute scores (gral, verticality, speed), SVM boundaries, ``w + α n`` edits and reports
* ``crowd``      -- variations around one latent, rendered as one scene
* ``inversion``  -- optimisation into W+ (representation + FK-position loss)

Import the submodule you need (``from modi.models.modi.latent import space``); the package itself imports nothing.
"""
