"""Map building: range-image normals, ground labels, Poisson meshes per tile, ground simplification, and
the mesh map the localizer renders from."""
