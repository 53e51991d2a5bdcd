"""jaxmap: neural implicit 3D mapping in JAX (N3-Mapping and transformable neural implicit maps)."""
import os as _os
import sys as _sys

__version__ = "0.1.0"


def _enable_compilation_cache():
    # For library users as for the CLI (see jaxmap.compile_cache). Before jax is imported the
    # environment is enough and keeps `import jaxmap` light; after, the config is updated.
    from jaxmap import compile_cache

    path = compile_cache.cache_dir()
    explicit = "JAXMAP_CACHE_DIR" in _os.environ  # ours, set by the user: it wins over an inherited JAX one
    if not path:
        if explicit:
            _os.environ.pop("JAX_COMPILATION_CACHE_DIR", None)
        return
    if "jax" in _sys.modules:
        compile_cache.enable(path)
    elif explicit:
        _os.environ["JAX_COMPILATION_CACHE_DIR"] = path
        _os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS",
                               _os.environ.get("JAXMAP_CACHE_MIN_COMPILE_S", "0.5"))
    else:
        _os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", path)
        _os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS",
                               _os.environ.get("JAXMAP_CACHE_MIN_COMPILE_S", "0.5"))


_enable_compilation_cache()


def __getattr__(name):
    # Lazy, so `import jaxmap` stays light and the CLI starts fast.
    if name == "N3Mapper":
        from jaxmap.n3.mapper import N3Mapper

        return N3Mapper
    raise AttributeError(name)
