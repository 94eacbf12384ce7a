"""`cpu-short` with Transformer 1 reading the line between each slot's seen latents: a candidate.

A cube that lands out of sight and rests there is filled from the seen latents on both sides of
the gap, not found by attention from the [M] token alone. It lifts permanence S1 under the MSE
score and loses lines of the NLL to the shipped xpl on every seed carded so far, so it is not the
default (docs/decisions.md, "Transformer 1 reads the line between seen latents").
"""
from dataclasses import replace

from . import cpu_short

SHORT = cpu_short.RECIPE

RECIPE = replace(SHORT, name="cpu-line",
                 xpl=replace(SHORT.xpl, fill_from_neighbours=True, line_between_only=True))
