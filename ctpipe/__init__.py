"""ctpipe: rotation angles of every view of a cone-beam CT scan, estimated from its projections.

Start with :class:`ctpipe.pipeline.Pipeline`, :class:`ctpipe.geometry.Geometry` and the
model in :mod:`ctpipe.model`; ``docs/`` has the derivation and the plugin guide.
"""

__version__ = "0.1.0"
