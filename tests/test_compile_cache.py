"""The persistent compilation cache is kept per CPU: an XLA:CPU executable loaded on a CPU other than
the one it was compiled for can abort the process, so two CPUs must never share a folder."""
import os

from jaxmap import compile_cache

_AVX512 = "processor\t: 0\nmodel name\t: Xeon\nflags\t\t: sse avx2 avx512f\n\nprocessor\t: 1\nmodel name\t: Xeon\nflags\t\t: sse avx2 avx512f\n"
_AVX2 = "processor\t: 0\nmodel name\t: Xeon\nflags\t\t: sse avx2\n"


def test_host_key_separates_cpus_that_differ_in_flags_or_model():
    assert compile_cache.host_key(_AVX512) != compile_cache.host_key(_AVX2)
    assert compile_cache.host_key(_AVX2) != compile_cache.host_key(_AVX2.replace("Xeon", "EPYC"))


def test_host_key_is_stable_for_one_cpu():
    # Flag order and the other cores' lines do not change the key; the key is a folder name.
    reordered = "processor\t: 0\nmodel name\t: Xeon\nflags\t\t: avx512f sse avx2\n"
    assert compile_cache.host_key(_AVX512) == compile_cache.host_key(reordered)
    key = compile_cache.host_key()
    assert key == compile_cache.host_key() and len(key) == 12 and os.sep not in key


def test_default_cache_folder_is_per_host():
    assert compile_cache.DEFAULT_DIR == os.path.join(compile_cache.ROOT_DIR, compile_cache.host_key())


def test_programs_built_counts_each_new_program_once():
    """The counter the remap tests rely on sees a program jax has to build (a listener on an event jax
    no longer sends would count nothing, and every `built == []` would pass), and not a cached call."""
    import jax
    import numpy as np

    f = jax.jit(lambda x: x * 3 + 1)
    x = np.arange(7, dtype=np.float32)       # host input: no device-side fill program of its own
    with compile_cache.programs_built() as built:
        f(x)
    assert len(built) == 1
    with compile_cache.programs_built() as built:
        f(x)
    assert built == []
