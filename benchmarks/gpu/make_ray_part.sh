#!/usr/bin/env bash
# Prepares .ray1/ .ray2/ .ray3/ in the project root: Ray (core, no dashboard client, no
# libraries: what `executor: ray` needs) and its pure-Python needs for the device machine's
# Python 3.12, stripped and xz-compressed (~26 MB), cut in three parts that travel beside .wp1,
# .wp2 and .wp3 (see run.sh); `run.sh setup` unpacks them into /tmp/site.
set -euo pipefail
root=$(git rev-parse --show-toplevel); cd "$root"
for d in .ray1 .ray2 .ray3; do grep -qx "/$d/" .git/info/exclude 2>/dev/null || echo "/$d/" >> .git/info/exclude; done
RAY=${RAY_VERSION:-$(python3 -c "import importlib.metadata as m; print(m.version('ray'))")}
t=$(mktemp -d)
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
  --platform any -d "$t" "ray==$RAY" click filelock jsonschema jsonschema-specifications \
  referencing rpds-py attrs msgpack protobuf
mkdir "$t/x" && (cd "$t/x" && for w in "$t"/*.whl; do unzip -q -o "$w"; done
  rm -rf ray/jars ray/rllib ray/data ray/serve ray/train ray/tune ray/llm ray/dashboard/client
  strip --strip-unneeded ray/_raylet.so ray/core/src/ray/gcs/gcs_server ray/core/src/ray/raylet/raylet
  find . -name __pycache__ -prune -exec rm -rf {} +
  tar -cf - . | xz -T0 -6 > "$t/ray.tar.xz")
rm -rf .ray1 .ray2 .ray3 && mkdir .ray1 .ray2 .ray3
# part sizes: what fits beside .wp1 (45 MiB), .wp2 + .dep, .wp3 + .whl + .gl + .nvj in 64 MiB
# (dd, not `tail | head`: head closing the pipe early fails the script under pipefail)
dd if="$t/ray.tar.xz" of=.ray1/rp.0 bs=1M iflag=count_bytes count=14000000 status=none
dd if="$t/ray.tar.xz" of=.ray2/rp.1 bs=1M iflag=skip_bytes,count_bytes skip=14000000 \
  count=8000000 status=none
dd if="$t/ray.tar.xz" of=.ray3/rp.2 bs=1M iflag=skip_bytes skip=22000000 status=none
rm -rf "$t"
du -sh .ray1 .ray2 .ray3
