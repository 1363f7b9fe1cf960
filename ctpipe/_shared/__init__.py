"""Helpers every layer shares and no user calls: argument checks and short reprs for messages
(:mod:`~ctpipe._shared.checks`), the fast-math flags of the numba kernels
(:mod:`~ctpipe._shared.jit`), the lazy exports of the packages
(:mod:`~ctpipe._shared.lazy`), and the memory checks that refuse a request before allocating it
(:mod:`~ctpipe._shared.resources`). Private, like scikit-image's ``skimage._shared``: the names
may change without notice; the errors they raise are public (:mod:`ctpipe.errors`).
"""
