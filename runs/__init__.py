"""The run driver: which cards each stage still owes, the claims that keep two runs apart, the
executors that compute them and the writes of what came back. Between the kernel (``core``) and
the features, which register what a run needs from them through :mod:`core.hooks`."""
