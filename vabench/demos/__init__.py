"""Demonstration videos: one successful expert execution per family, RGB frames only.

    python -m vabench.demos build [--task T ...] [--out DIR] [--manifests DIR] [--force]

`build_demo(task, cache_dir)` builds or finds current a family's demonstration and returns its
`DemoInfo`; `load_demo(task, cache_dir)` returns the `Demo` the tools serve (JPEG frames in
order). Seed choice, frame rule and cache: `vabench.demos.build`; layout: `vabench.demos.store`.
"""

from vabench.demos.build import build_demo, demo_candidates, evaluation_seeds
from vabench.demos.store import Demo, DemoInfo, load_demo

__all__ = ["Demo", "DemoInfo", "build_demo", "demo_candidates", "evaluation_seeds", "load_demo"]
