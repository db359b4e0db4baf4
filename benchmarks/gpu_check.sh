#!/bin/bash
# GPU check (device machine only): core tests on the CUDA backend, then search throughput.
# Run from the repository root on a CUDA machine with jax installed (the device tool: carry
# .gpu/whl, wheels of equinox, optimistix, lineax and control that `pip download` fetched for
# that machine's Python); results under $OUT. Not part of CI: mfmjax needs no GPU.
cd "$(dirname "$0")/.."
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .gpu/whl/*.whl || exit 9
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
nvidia-smi -L; nproc
python3 -c "import jax, equinox, optimistix, lineax, numpy, scipy; jax.config.update('jax_enable_x64', True); import jax.numpy as jnp; x = jnp.ones(3); print('jax', jax.__version__, 'eqx', equinox.__version__, 'np', numpy.__version__, 'scipy', scipy.__version__, jax.devices(), (x @ x).dtype, x.devices())"
python3 -c "import mfmjax, jax; print('import ok', jax.default_backend(), jax.numpy.ones(2).dtype)"
SECONDS=0
timeout 270 python3 -m pytest -q -p no:cacheprovider -o addopts="" -n 8 --dist loadfile -ra tests/test_identify.py tests/test_gram_solve.py tests/test_observers.py tests/test_search.py tests/test_srivc.py tests/test_output_error.py tests/test_linalg.py tests/test_quadrature.py tests/test_modulating.py tests/test_online.py tests/test_estimate.py tests/test_refine.py tests/test_selection.py > $OUT/pytest.log 2>&1
echo "pytest rc=$? in $SECONDS s"; tail -60 $OUT/pytest.log
SECONDS=0
timeout 170 python3 benchmarks/search_throughput.py > $OUT/throughput.log 2>&1
echo "throughput rc=$? in $SECONDS s"; cat $OUT/throughput.log | tail -40
cp benchmarks/results/search_throughput.json $OUT/search_throughput_gpu.json 2>/dev/null
