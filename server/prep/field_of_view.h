// The body as the image holds it: where the image's border cuts the body (a cropped
// CT, or every CT's first and last slice), on which faces in patient terms and how
// much; the depth under the skin (map B) with or without those cut faces counted as
// skin; and whether the body mask looks like a body (one piece, a trunk's size).
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "core/scene.h"
#include "core/volume.h"

namespace palpsim {

/// One face of the grid where the body reaches the image's border.
struct CutFace {
  std::string name;              // the patient side it faces: anterior, posterior, left, right, superior, inferior
  int axis = 0;                  // the grid axis (0, 1, 2) perpendicular to the face
  bool high = false;             // the face at that axis' last index (else at its first)
  std::size_t body_voxels = 0;   // body voxels on the face
  double area_mm2 = 0;           // their area on the face (mm^2)
  double face_fraction = 0;      // body_voxels over the face's voxels
  double body_fraction = 0;      // body_voxels over every body voxel
};

/// The faces where the image cuts the body, and the one warning that names them.
struct FieldOfView {
  std::vector<CutFace> faces;    // faces with at least kMinCutAreaMm2 of body on them, in grid order
  std::string warning;           // one sentence naming the faces and how they are treated; "" when none
};

/// Body on a face from this area (mm^2) up counts as a cut: a fingertip's contact area,
/// so that a few voxels of body that graze the border (a partial-volume fringe) do not.
constexpr double kMinCutAreaMm2 = 100;

/// The patient side (LPS: +x left, +y posterior, +z superior) that the outward normal
/// of the grid's face at `axis` (its last index when `high`) points to most, from the
/// grid's direction matrix: "left", "right", "posterior", "anterior", "superior" or
/// "inferior".
std::string face_name(const Grid& g, int axis, bool high);

/// Finds the faces where `body` (a 0/1 mask) reaches the grid's border with at least
/// kMinCutAreaMm2, and words the warning, e.g. "the body is cut at the anterior and
/// superior faces: no skin there (prep.cut_faces = "skin": they count as skin)".
FieldOfView find_cut_faces(const Volume<std::uint8_t>& body, CutFaces mode);

/// B, the depth (mm) under the skin: the distance from each body voxel to the nearest
/// outside voxel centre (0 outside). With CutFaces::kSkin a layer of outside voxels
/// beyond every face of the grid counts too, so a body voxel on a cut face lies one
/// voxel under the skin, as one beside outside air does; with kOpen only the image's
/// own outside voxels count.
Volume<float> depth_under_skin_mm(const Volume<std::uint8_t>& body, CutFaces mode, int threads = 0);

/// What the body mask looks like: its pieces and its mean axial cross-section, with a
/// warning where that is no body's.
struct BodyCheck {
  int pieces = 0;                  // 6-connected pieces of the body mask holding kMinPieceFraction of it or more
  double largest_fraction = 0;     // the largest piece's share of the body's voxels
  double cross_section_cm2 = 0;    // body volume over the axial extent holding body (cm^2)
  std::vector<std::string> warnings;  // one sentence each; empty when the mask looks like a body
};

/// A body mask is one piece, its arms at most two more; pieces beyond kMaxBodyPieces,
/// or a largest piece under kMinLargestPieceFraction of the body, mean the air
/// threshold cut through soft tissue (an image not in HU with a threshold set too high).
constexpr int kMaxBodyPieces = 3;
/// Pieces under this fraction of the body are specks (a cable's end, a crumb of the
/// table), not fragments of the body, and are not counted.
constexpr double kMinPieceFraction = 0.01;
constexpr double kMinLargestPieceFraction = 0.8;
/// The mean axial cross-section (cm^2) of a trunk: an adult abdomen of 30 x 20 cm has
/// about 470 cm^2, a child's trunk from about 150, the widest adult trunk with arms
/// under 1500; outside these the mask holds noise, the table, or too little.
constexpr double kMinBodyCrossSectionCm2 = 150;
constexpr double kMaxBodyCrossSectionCm2 = 1500;

/// Checks `body` as BodyCheck says; `air_threshold` and `units` ("HU" or "image
/// units") go into the warnings, which name prep.air_threshold.
BodyCheck check_body(const Volume<std::uint8_t>& body, double air_threshold, const std::string& units);

/// The field of view as prep.json's "field_of_view" object: the treatment and each
/// cut face with its body voxels, area and fractions.
std::string field_of_view_json(const FieldOfView& fov, CutFaces mode);

}  // namespace palpsim
