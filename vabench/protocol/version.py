"""The version of the model-facing protocol: what a model sees, may do and is scored by.

Any change to the system prompt, the observation text, the actions and their semantics, the
reply rule, the learning stage, the passive views or the API defaults a model meets is a new
version. Every run directory's plan and every report carry it, so that scores measured under
different protocols are never pooled (docs/PROTOCOL.md lists what each point is and why).
"""

PROTOCOL_VERSION = "vabench-3"
