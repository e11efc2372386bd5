"""The command line and what it runs: ``cli`` (``mjx-supportfield``), ``bench`` and ``newton_bench``
(timing against stock MuJoCo Warp and Newton), ``compare`` (contacts against MuJoCo C) and
``exact`` (exact overlaps of convex shapes, compare's judge)."""
