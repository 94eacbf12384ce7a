"""`cpu` with Transformer 1 blind to the walls: the step between `cpu` and the default `cpu-short`.

Some perception draws give walls latents close to a cube's, and Transformer 1 then fills a
hidden cube with the wall; reading no wall keeps its fills on objects (docs/decisions.md,
"Transformer 1 blind to the walls"; docs/results.md, "The walls recipe from nothing").
"""
from dataclasses import replace

from . import cpu

RECIPE = replace(cpu.RECIPE, name="cpu-walls", xpl=replace(cpu.RECIPE.xpl, refill_ignores_walls=True))
