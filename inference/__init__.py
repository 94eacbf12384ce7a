"""The Pyro analysis-by-synthesis model: amortised hidden-object proposal, NLL surprise.

Imported as `xvoe.inference` (xvoe/inference links to this folder); built on xvoe's models and
evaluation layers, and only xvoe's applications and public API import it.
"""
