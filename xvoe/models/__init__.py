"""The networks (layer 2): perception, XPL's Transformers and dynamics, PhyDNet, and slot compositing."""
