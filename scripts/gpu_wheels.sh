#!/usr/bin/env bash
# The wheels benchmarks/gpu_offline.sh installs on a GPU machine without network, made here (package index and
# CUDA's nvcc at hand, no GPU needed):
#
#   bash scripts/gpu_wheels.sh WHEELS
#
# Downloads, for the GPU machine's Python (PY, default 3.12; manylinux x86-64), the packages the project needs
# beyond that machine's own torch, Lightning and test tools (PACKAGES, pinned to the versions the CPU tests
# use), and compiles gsplat's CUDA extension (GSPLAT, default 1.5.3) against the torch the machine runs (TORCH,
# default 2.11.0, the CUDA build the package index serves) for its GPU (ARCH, default 9.0: H100 / H200), with
# nvcc from CUDA_HOME (default /usr/local/cuda), into a gsplat wheel that imports without compiling. The build
# runs in BUILD (default /tmp/gsplat-build: a Python PY virtual environment with that torch, about 5 GB) and
# takes minutes (about 5 on 2 cores); MAX_JOBS (default 2) compiler processes run at once.
set -euo pipefail

[[ $# -eq 1 ]] || { echo "usage: bash scripts/gpu_wheels.sh WHEELS" >&2; exit 2; }
WHEELS=$(realpath -m "$1")
PY=${PY:-3.12}
TORCH=${TORCH:-2.11.0}
GSPLAT=${GSPLAT:-1.5.3}
ARCH=${ARCH:-9.0}
CUDA_HOME=${CUDA_HOME:-/usr/local/cuda}
BUILD=${BUILD:-/tmp/gsplat-build}
PACKAGES=${PACKAGES:-kornia==0.9.0 kornia_rs==0.2.0 jsonargparse==4.53.0 docstring_parser==0.18.0
    typeshed_client==2.15.0 omegaconf==2.4.0 webdataset==1.0.2 braceexpand==0.1.7}
[[ -x $CUDA_HOME/bin/nvcc ]] || { echo "gpu_wheels.sh: no nvcc in $CUDA_HOME/bin (set CUDA_HOME)" >&2; exit 2; }
interpreter=
for candidate in "$(command -v "python$PY")" "$HOME"/.pyenv/versions/"$PY".*/bin/python; do
    if [[ -x $candidate ]] && "$candidate" -c '' 2>/dev/null; then interpreter=$candidate && break; fi
done
[[ -n $interpreter ]] || { echo "gpu_wheels.sh: no Python $PY here (python$PY or pyenv)" >&2; exit 2; }
mkdir -p "$WHEELS" "$BUILD/ext" "$BUILD/packed"
platforms=(--platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64)
# shellcheck disable=SC2086  # PACKAGES is a list of requirements
python3 -m pip download -q --no-deps --only-binary=:all: --python-version "$PY" --implementation cp \
    "${platforms[@]}" -d "$WHEELS" $PACKAGES

[[ -x $BUILD/venv/bin/python ]] || "$interpreter" -m venv "$BUILD/venv"
"$BUILD/venv/bin/pip" install -q "torch==$TORCH" "setuptools<82" wheel ninja numpy
"$BUILD/venv/bin/pip" download -q --no-deps -d "$BUILD" "gsplat==$GSPLAT"
rm -rf "$BUILD/unpacked" && "$BUILD/venv/bin/wheel" unpack -d "$BUILD/unpacked" "$BUILD/gsplat-$GSPLAT-py3-none-any.whl"
package=$BUILD/unpacked/gsplat-$GSPLAT/gsplat
# gsplat imports gsplat.csrc when it exists and compiles nothing: build its sources as that module.
CUDA_HOME=$CUDA_HOME TORCH_CUDA_ARCH_LIST=$ARCH MAX_JOBS=${MAX_JOBS:-2} PATH="$BUILD/venv/bin:$PATH" \
    "$BUILD/venv/bin/python" - "$package/cuda" "$BUILD/ext" <<'EOF'
import glob, sys, time
from torch.utils.cpp_extension import load

cuda, build = sys.argv[1:]
sources = sorted(glob.glob(f"{cuda}/csrc/*.cu") + glob.glob(f"{cuda}/csrc/*.cpp")) + [f"{cuda}/ext.cpp"]
start = time.time()
load("csrc", sources, extra_cflags=["-O3", "-Wno-attributes"], extra_cuda_cflags=["-O3", "-use_fast_math"],
     extra_include_paths=[f"{cuda}/include/", f"{cuda}/csrc/third_party/glm"], build_directory=build)
print(f"gsplat's CUDA extension compiled in {time.time() - start:.0f} s")
EOF
cp "$BUILD/ext/csrc.so" "$package/csrc.so"
strip --strip-unneeded "$package/csrc.so"
rm -f "$WHEELS"/gsplat-*.whl
"$BUILD/venv/bin/wheel" pack -d "$BUILD/packed" "$BUILD/unpacked/gsplat-$GSPLAT"
tag=cp${PY/./}
"$BUILD/venv/bin/wheel" tags --remove --python-tag "$tag" --abi-tag "$tag" --platform-tag linux_x86_64 \
    "$BUILD/packed/gsplat-$GSPLAT-py3-none-any.whl" >/dev/null
mv "$BUILD/packed/gsplat-$GSPLAT-$tag-$tag-linux_x86_64.whl" "$WHEELS/"
du -sh "$WHEELS"
ls "$WHEELS"
