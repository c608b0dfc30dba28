"""The only package that imports bpy: it renders SceneSpec dicts and nothing else."""
