"""ctpipe's own stages, each module a plugin listed in ``ctpipe.plugins.BUILTIN_PLUGINS``."""
