"""``python -m simbed.scenes.towngen``: regenerate the towns shipped in ``scenes/``."""

from simbed.scenes.towngen import generate_shipped

for nm, info in generate_shipped().items():
    print(f"{nm}: {len(info.nodes)} nodes, {len(info.edges)} roads, {info.total_length_m:.0f} m of road")
