"""World-side effects: what real cameras and real light add to captures.

Implemented differently from recon's own (model-side) effect modules on purpose: a world that
mirrors the model proves nothing. See data_synth/effects/base.py for the interface.
"""
