"""Fused member-pair kernels of a population pass: member tables, pair functions and
the reductions over members. ``registry`` lists the profiles (add one there, recipe in
``CONTRIBUTING.md``); ``epl`` and ``nfw`` hold the tables and pairs; ``sums`` the kernels.
"""
