"""The Pyro analysis-by-synthesis model: amortised hidden-object proposal, NLL surprise.

Depends on xvoe; xvoe never imports it.
"""
