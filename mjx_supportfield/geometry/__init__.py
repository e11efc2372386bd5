"""Device geometry and its install-time builders: support queries (``support``) and the support
fields they read (``support_field``, ``hull_graph``), the penetration solvers (``mpr``, ``gjk``),
multi-contact by tilts and face clipping (``multicontact``, ``faceclip``), the shapes' device
records (``shapes``) and signed-distance fields (``sdf``); install's results cached on disk
(``disk_cache``). Its kernels run at install (building fields and SDFs), never at step time."""
