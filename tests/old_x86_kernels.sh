#!/usr/bin/env bash
# Run a command under the CPU kernels of an old x86-64 machine, whatever this one is: OpenBLAS'
# Sandybridge kernels, numpy's baseline SIMD only, ATen's "default" (no AVX) and oneDNN's SSE4.1
# kernels, glibc's libm without its FMA/AVX2 variants. Results that must not depend on the CPU
# (docs/DETERMINISM.md) are checked by running the suite under it:
#   tests/old_x86_kernels.sh .venv/bin/python -m pytest -q
set -euo pipefail
if [ "$(uname -m)" != x86_64 ]; then
  echo "old_x86_kernels.sh: x86-64 only; running the command unchanged" >&2
  exec "$@"
fi
python=${PYTHON:-$(dirname "$0")/../.venv/bin/python}
flags=$(grep -m1 '^flags' /proc/cpuinfo)
# Forcing a core type this CPU cannot run would crash: Sandybridge needs AVX.
if [[ " $flags " == *" avx "* ]]; then export OPENBLAS_CORETYPE=Sandybridge; else export OPENBLAS_CORETYPE=Prescott; fi
NPY_DISABLE_CPU_FEATURES=$("$python" -c 'from numpy.core._multiarray_umath import __cpu_features__ as f, __cpu_baseline__ as b; print(" ".join(k for k, on in f.items() if on and k not in b))')
export NPY_DISABLE_CPU_FEATURES
export ATEN_CPU_CAPABILITY=default ONEDNN_MAX_CPU_ISA=SSE41
export GLIBC_TUNABLES=glibc.cpu.hwcaps=-AVX2,-FMA,-AVX512F
echo "kernels: OPENBLAS_CORETYPE=$OPENBLAS_CORETYPE ATEN_CPU_CAPABILITY=$ATEN_CPU_CAPABILITY ONEDNN_MAX_CPU_ISA=$ONEDNN_MAX_CPU_ISA GLIBC_TUNABLES=$GLIBC_TUNABLES NPY_DISABLE_CPU_FEATURES='$NPY_DISABLE_CPU_FEATURES'" >&2
exec "$@"
