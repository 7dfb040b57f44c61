"""statmc.nn: small PyTorch networks whose outputs plug into statmc's kernels.

Installed as ``statmc.nn``; needs the optional ``torch`` extra (``pip install
'statmc[nn]'``, pinned to the CPU build ``torch==2.13.0``).  Empty for now.
"""
