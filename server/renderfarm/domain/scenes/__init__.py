"""Scenes as uploaded: glTF/GLB validation, packing into one .glb, bundles, environment maps."""
