"""StomachUnfoldEval: evaluation of the unfolding methods, beside the library and never shipped in the extension.

``phantom`` (synthetic CTs with known markers), ``markers`` (marker visibility and pairwise distortion against
the truth), ``bench`` (``stomach-unfold bench``: phantom set, real CTs, sweeps, Table 1, peers, stability,
speed). The methods themselves, our own and the peers, are in ``StomachUnfoldLib.methods``.
"""
