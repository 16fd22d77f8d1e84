"""The object model's geometry sources, one per file: procedural shapes, triangle meshes and 3DGS PLY files."""
