"""The map the localizer reads: a folder of tiles and its index (``store``), the whole map in memory
(``meshmap``, also the folder's reader and writer), a map seen within a memory budget (``view``, with its
tile ``cache``), the coarse level (``coarse``) and the older single-file format's reader (``ply_v1``). Both
kinds of map follow the ``meshmap.Map`` protocol. It imports the foundation and the sensing core; the
builder (``rangemcl.mapping``) and the localizer build on it."""
