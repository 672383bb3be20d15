"""Motion file formats: BVH (:mod:`modi.io.bvh`) and glTF 2.0 (:mod:`modi.io.gltf`).

Kept apart from the models so that reading/writing files never pulls in torch.
"""
