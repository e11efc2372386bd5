"""Launch and buffers: what every stage shares at step time. The stage contract (``stage``), the
rows of ``d.contact`` each world owns, the writer through them and the structs every writer takes
(``contact_quota``), the contacts' canonical order (``contact_sort``), the grid and register limits
of the kernels (``grid``), and the notes on kernel compilation at first use (``first_use``)."""
