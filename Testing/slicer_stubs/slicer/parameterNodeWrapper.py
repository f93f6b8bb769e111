"""Test-only stand-in for Slicer's parameterNodeWrapper: typed fields kept on the wrapper, defaults applied."""


def parameterNodeWrapper(cls):
    annotations = dict(getattr(cls, "__annotations__", {}))
    defaults = {name: getattr(cls, name, None) for name in annotations}

    class Wrapped:
        __name__ = cls.__name__
        __doc__ = cls.__doc__

        def __init__(self, node=None):
            object.__setattr__(self, "parameterNode", node)
            for name, value in defaults.items():
                object.__setattr__(self, name, value)

        def __setattr__(self, name, value):
            if name not in annotations:
                raise AttributeError(f"{cls.__name__} has no parameter {name!r}")
            object.__setattr__(self, name, value)

    return Wrapped
