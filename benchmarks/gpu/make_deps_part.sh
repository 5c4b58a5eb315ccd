#!/usr/bin/env bash
# Prepares .dep/ in the project root: wheels of vabench's pure-Python-side dependencies that
# the device machine's image may lack (aiohttp, rich, pyyaml, pytest and theirs; its image has
# pillow, for torchvision), for Python 3.12 on x86_64, about 6 MB. `run.sh setup` installs them into /tmp/site only when an import
# of one of them fails there. Carried beside .wp2 (see run.sh).
set -euo pipefail
root=$(git rev-parse --show-toplevel); cd "$root"
grep -qx "/.dep/" .git/info/exclude 2>/dev/null || echo "/.dep/" >> .git/info/exclude
rm -rf .dep && mkdir .dep
python3 -m pip download -q --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 --platform any -d .dep aiohttp rich pyyaml pytest
du -sh .dep
