"""Where the car drives: generated towns (``towngen``), a mesh world made a scene (``import_scene``), the
ground and the roads of any scene (``scene_ground``, ``lanes``) and the routes over them (``routes``)."""
