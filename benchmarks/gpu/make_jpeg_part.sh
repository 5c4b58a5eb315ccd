#!/usr/bin/env bash
# Prepares .nvj/ in the project root: nvImageCodec (GPU JPEG) and nvJPEG for the device
# machine's Python 3.12 and CUDA 13, cut down to what JPEG encoding needs (the wheels are 29 MB,
# more than fits beside .wp3 + .whl in one call; this is about 8 MB) plus simplejpeg's wheel.
# On the device, in the call that carries .nvj:
#   tar -xJf .nvj/nvj.tar.xz -C /tmp/site && pip install --no-deps --target /tmp/site .nvj/*.whl
#   export LD_LIBRARY_PATH=/tmp/site/nvidia/cu13/lib:$LD_LIBRARY_PATH
set -euo pipefail
root=$(git rev-parse --show-toplevel); cd "$root"
grep -qx "/.nvj/" .git/info/exclude 2>/dev/null || echo "/.nvj/" >> .git/info/exclude
t=$(mktemp -d)
plat="--platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64"
dl() { python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp $plat -d "$t" "$@"; }
dl "nvidia-nvimgcodec-cu13" "nvidia-nvjpeg" "simplejpeg"
mkdir -p "$t/x" && (cd "$t/x" && for w in "$t"/nvidia_*.whl; do unzip -q -o "$w"; done)
n="$t/x/nvidia/nvimgcodec"
find "$n" -name 'nvimgcodec_impl.cpython-*' ! -name '*cpython-312-*' -delete
find "$n/extensions" -type f ! -name 'libnvjpeg_ext*' ! -name 'libjpeg_turbo_ext*' -delete
rm -rf "$n/tools" "$n/include"
rm -rf .nvj && mkdir .nvj
(cd "$t/x" && tar -cf - nvidia | xz -T0 -6 > "$root/.nvj/nvj.tar.xz")
cp "$t"/simplejpeg-*.whl .nvj/
rm -rf "$t"
du -sh .nvj/*
