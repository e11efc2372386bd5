"""The step-time stages, in the order the collider launches them: bounding boxes (``aabb``), the
broad phase (``broadphase``, with the pair routing of ``routing``), the narrow phase
(``narrowphase``, warm-started by ``warmstart``), the multi-contact pass (``multicontact_pass``),
the deep-pair check (``deep_pairs``), heightfields (``heightfield``, ``hfield_closed_form``, with
their cells' and windows' device functions), non-convex meshes (``nonconvex``) and the stage ends
(``stage_ends``). Each owns its kernels and a stage class (``launch/stage.py``'s contract: model-time facts,
per-Data buffers, one ``launch``); candidate
contacts merged before writing are ``candidates``'s."""
