"""The networks, pure torch and numpy: CNMP (:mod:`.cnmp`), its training draw (:mod:`.sampling`), its numpy twin
for execution (:mod:`.numpy_cnmp`), the mixture decoder (:mod:`.mixture`) and the SM normalizer (:mod:`.normalizer`).
Imports no other room of the package."""
