"""A non-LLM reference agent that solves VA-Bench tasks from what a model sees.

It reads only the request an embedded-server policy receives (the observation text and the
images), and never imports the simulator, the tasks or the renderer: `request` parses the
observation and the agent's own memo, `vision` and `perception` find the objects in the
topdown view, `geometry` turns pixels into world points with the view's public geometry,
`families` names the task family and holds its plans (`plans` for the single-arm families),
`executor` runs a plan one decision at a time, `policy` is the embedded policy.
See docs/REFERENCE_AGENT.md.
"""

from vabench.reference_agent.policy import ReferenceServo, reply_text

__all__ = ["ReferenceServo", "reply_text"]
