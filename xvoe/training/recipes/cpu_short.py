"""The default recipe: `cpu-walls` inside the pipeline's 30 minutes on 2 cores.

Transformer 2 is left to the proposal stage (the joint step costs a third less), the
perception and XPL stages are shorter, and the XPL and proposal stages keep a moving average
of their weights, so that a shorter run does not end on a noisy last step; a quarter of the
perception's frames show an object in the air, and the proposal stage draws half its batches
from blocking videos. The shipped models come from its seed 0 (docs/decisions.md, "The default
recipe"; docs/models.md).
"""
from dataclasses import replace

from . import cpu_walls

WALLS = cpu_walls.RECIPE

RECIPE = replace(
    WALLS, name="cpu-short",
    # a quarter of each perception batch shows a ball or cube off the floor: a few percent of all
    # frames otherwise, and falling cubes were encoded as nothing (docs/decisions.md, "Frames of
    # objects in the air")
    perception_train=replace(WALLS.perception_train, steps=4_000, decay_steps=3_333, airborne_share=0.25),
    xpl=replace(WALLS.xpl, joint_proposal=False),
    xpl_train=replace(WALLS.xpl_train, steps=9_000, decay_steps=6_000, average_decay=0.999),
    # half of each proposal batch from blocking videos with a wall: there a hidden cube's place shows
    # in the ball's path; most hidden objects elsewhere leave no trace to learn from
    proposal_train=replace(WALLS.proposal_train, average_decay=0.999, focus_group="blocking", focus_share=0.5),
)
