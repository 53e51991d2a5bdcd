"""jaxmap: neural implicit 3D mapping in JAX (N3-Mapping and transformable neural implicit maps)."""
__version__ = "0.1.0"


def __getattr__(name):
    # Lazy, so `import jaxmap` stays light and the CLI starts fast.
    if name == "N3Mapper":
        from jaxmap.n3.mapper import N3Mapper

        return N3Mapper
    raise AttributeError(name)
