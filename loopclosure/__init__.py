"""SSM-VPR (Camara & Preucil, ECMR 2019) place recognition, usable on its own."""
