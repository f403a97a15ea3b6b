"""The report's table of Hertz's blocks on the half-space (palpsim-bench accuracy --halfspace,
bench/hertz_halfspace_bench.cpp): each block pressed with its faces at rest and with its faces
where the half-space puts them, against Hertz's force and surface profile, beside the FEM rows of
the elastic study (accuracy --elastic) for the same Poisson ratio and depth."""


def halfspace_markdown(hs, elastic, fmt, met, band_for):
    """The section's lines. `hs` is the half-space JSON, `elastic` the elastic study's (for its FEM
    columns; may be None); fmt, met and band_for are the report's formatters."""
    fem = {}
    for h in ((elastic or {}).get("references") or {}).get("hertz", []):
        fem.setdefault((h["nu"], h["depth_mm"]), h)
    L = ["### (iii) and (iv) on a piece of the half-space", ""]
    L.append(f"Measured {hs['date']} on {hs['host_cpu']} ({hs['host_threads']} threads), commit {hs['commit']} "
             "(palpsim-bench accuracy --halfspace, bench/hertz_halfspace_bench.cpp). Hertz's formulas are for a "
             "half-space, whose surface tens of mm from the finger still sinks by (1 - nu^2) F / (pi E r); the "
             "blocks above hold their faces at rest, which makes them stiffer and their surface flatter than Hertz's. "
             "Here the same element on blocks of n^3 voxels of 1 mm (the skin the node layer n - "
             f"3, a sphere of {hs['radius_mm']:g} mm, {hs['hu']:g} HU) is solved twice: with the faces at rest, "
             "and with the body nodes of the faces held at Boussinesq's displacement of a point load equal to "
             "the finger's force (Johnson, Contact Mechanics, 3.22), the force from the solve before until it "
             f"moves by less than {100 * hs['force_settled']:g} %. What is left is the model's own error, the "
             "quantity the FEM with cells of the voxels' 1 mm (on a 1000 mm domain) measures for the same "
             "element. Bands: the smallest of 1, 2, 5, 10, 20, 50 % the converged FEM meets, and the one the "
             "FEM at 1 mm meets.")
    L.append("")
    L.append("| block | nu | d mm (d/R) | Hertz N | faces at rest / Hertz | half-space faces / Hertz | "
             "FEM 1 mm / Hertz | goal 5 % | profile %: faces at rest | half-space faces | FEM 1 mm | "
             "FEM converged (band) | within the converged FEM's band | within the 1 mm FEM's band | updates | "
             "CG steps | s |")
    L.append("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in hs["rows"]:
        f = fem.get((r["nu"], r["depth_mm"])) or {}
        fv, fc = f.get("fem_voxel") or {}, f.get("fem") or {}
        band_c, band_v = band_for(fc.get("profile_pct")), band_for(fv.get("profile_pct"))
        prof = r["halfspace_profile_pct"]
        L.append(f"| {r['block_n']}^3 | {r['nu']:g} | {r['depth_mm']:g} (1/{hs['radius_mm'] / r['depth_mm']:.0f}) | "
                 f"{fmt(r['hertz_n'], 4)} | {r['held_ratio']:.3f} | {r['halfspace_ratio']:.3f} | "
                 f"{fmt(fv.get('ratio'))} | {met(100 * (r['halfspace_ratio'] - 1), 5.0)} | "
                 f"{fmt(r['held_profile_pct'])} | {fmt(prof)} | {fmt(fv.get('profile_pct'))} | "
                 f"{fmt(fc.get('profile_pct'))} ({'-' if band_c is None else f'{band_c:g}'}) | "
                 f"{'-' if band_c is None else met(prof, band_c)} | {'-' if band_v is None else met(prof, band_v)} | "
                 f"{r['face_updates']}{'' if r['settled'] else ' (not settled)'} | {r['iterations']} | "
                 f"{fmt(r['seconds'])} |")
    L.append("")
    return L
