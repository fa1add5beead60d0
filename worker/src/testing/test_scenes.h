// Scenes built by the tests (not part of the worker binary).
#pragma once

#include <string>
#include <vector>

#include "scene/scene.h"

namespace rf {
namespace testing {

// Two triangles p0 p1 p2 and p0 p2 p3 (front face = counter-clockwise as listed).
void add_quad(SceneDescription* desc, Vec3 p0, Vec3 p1, Vec3 p2, Vec3 p3, uint32_t material);

// A Lambertian square of albedo rho (side 4, centered at the origin in z = 0, facing +z) under
// a one-sided emissive a x b rectangle of radiance L centered above the origin at height c and
// facing down; camera at `eye` looking at the origin with field of view yfov.
SceneDescription plane_under_emitter(float rho, float L, float a, float b, float c, Vec3 eye,
                                     float yfov);

// A small glTF 2.0 scene as JSON text with its buffer as a base64 data: URI: an indexed
// (uint16) floor quad, a non-indexed emissive quad (emissiveStrength 4) under a translated and
// scaled parent node, a camera on a rotated node, and an unlit LINES primitive on the floor.
std::string small_gltf_json();
// small_gltf_json's scene with two LINEAR animations over t in [0, 2]: 0 "slide" moves the
// light's parent from (0, 2, 0) to (1.5, 2, 0), 1 "shrink" scales the floor from 1 to
// (0.5, 1, 0.5).
std::string animated_gltf_json();

// A glTF scene whose camera rays' first hits are on known glTF nodes and materials (the
// Instance and Material rows), seen by an orthographic camera looking down -z at a 16 x 12
// image whose pixels are 0.5 x 0.5 units: a grid of 4 x 3 cells of 4 x 4 pixels, each cell a
// 2 x 2 quad (facing +z, its edges on pixel edges) or nothing, as ids_gltf_cells lists them.
// It has a mesh used by one node (merged into the world triangles, after a degenerate
// triangle the Scene drops), a mesh shared by two nodes (instances), a node whose mesh
// EXT_mesh_gpu_instancing draws twice, a morphed (flattened) mesh, a MASK quad that stops the
// camera rays in front of it, a BLEND quad of alpha 0 and a MASK one below its cutoff that let
// them through, a primitive without a material, two LINES primitives of one node (one
// without a material), KHR_materials_variants mappings (variant 0, "v0") and a node without a
// mesh whose children come earlier in "nodes"; nodes, meshes and the scene's roots are in
// different orders. The lines are one pixel wide at an image height of 12 (load it with
// LoadOptions::image_height = 12). animated: node 2 (an instance of the shared mesh) slides
// along z and node 4's morph weight goes from 0 to 1 over t in [0, 1] ("move"), which change
// no pixel's first hit (an animated layout with one moving node and one deformed node).
std::string ids_gltf_json(bool animated = false);
// A cell of ids_gltf_json's image: its top-left pixel (x0, y0), what its 4 x 4 pixels' camera
// rays hit first, and the Instance and Material rows there (the glTF node and material plus
// one, 0 for none), and the Material row with variant "v0" selected. Its 2 x 2 inner pixels
// see nothing else whatever the position of a sample inside them.
struct IdCell {
  uint32_t x0, y0;
  const char* what;
  uint32_t instance, material, variant_material;
};
const std::vector<IdCell>& ids_gltf_cells();

// JSON members "accessors", "bufferViews" and "buffers" (no surrounding braces) of a unit
// quad: z = 0, x and y in [-1, 1], facing +z, as accessors 0 POSITION, 1 NORMAL,
// 2 TEXCOORD_0 = ((x + 1) / 2, (1 - y) / 2) (glTF's v points down the image) and 3 uint16
// indices.
std::string quad_gltf_buffers_json();

// A folder of the running test's own, created on first use: ::testing::TempDir()/
// rf-<pid>-<Suite>.<Test> (ctest -j runs the instances of a parameterized test, and every
// other test, in processes of their own at once; fixed file names in the shared temporary
// folder let one read another's half-written file). Removed with everything in it when the
// test process exits. `name` is appended as a path inside it.
std::string test_path(const std::string& name);

// bytes as a base64 data: URI of the given MIME type.
std::string data_uri(const std::string& mime_type, const std::vector<unsigned char>& bytes);

// A PNG of width x height 8-bit pixels (channels per pixel, row-major from the top; colours
// not premultiplied by alpha) as a data: URI.
std::string png_data_uri(int width, int height, int channels,
                         const std::vector<unsigned char>& pixels);
// The same pixels in another format OpenImageIO writes ("webp", "avif": lossy, at quality
// 100), as a data:image/<format> URI.
std::string image_data_uri(const std::string& format, int width, int height, int channels,
                           const std::vector<unsigned char>& pixels);

// A flat-shaded (no vertex normals: shading normal = geometric normal) UV sphere of
// 2 * rings * (segments) triangles, outward facing.
void add_sphere(SceneDescription* desc, Vec3 center, float radius, uint32_t material,
                int rings = 48, int segments = 96);

// Camera looking from eye to target with +Y-ish up.
Camera look_at(Vec3 eye, Vec3 target, float yfov);

}  // namespace testing
}  // namespace rf
