// OBJ / PLY / STL import through OpenMesh's format readers, ASCII OFF through our own.
//
// OpenMesh's readers talk to a BaseImporter. Its stock ImporterT builds a half-edge mesh
// and silently drops every face that would make it non-manifold ("complex edge"), which
// would change the geometry we train on. PolygonSoup below is our own BaseImporter: it
// records vertices, per-vertex normals and faces exactly as read and builds no
// connectivity, so nothing is lost; everything is validated afterwards.
//
// ASCII OFF has a reader of its own here (read_ascii_off): OpenMesh 9's OFF reader reads
// the CGAL data set's files (ChineseDragon-10kv.off, armadillo.off) but returns an empty
// mesh for any OFF file with a '#' comment line, which the format allows and many files
// (CGAL's own writers included) have; OFF is simple enough that a strict line-based reader
// with line numbers in its errors is less code than working around that. Binary OFF is
// refused: OpenMesh 9 reads its counts in the host's byte order, where the format's are
// big-endian, so a file written to the format became tens of millions of garbage faces, and
// garbage counts made it reserve gigabytes (found by fuzz_import). OpenMesh trusts the
// element counts of PLY headers and the list lengths of PLY bodies and reserves memory for
// them (a 3.5e9-vertex header makes it allocate tens of GiB), so those are checked against
// the file size first; and it reads a PLY body under a header written from the checked one
// (ply_header_for_openmesh), since its own reading of a header diverges from the format's.
#include "scene_internal.hpp"

#include <OpenMesh/Core/IO/IOManager.hh>
#include <OpenMesh/Core/IO/MeshIO.hh>
#include <OpenMesh/Core/IO/importer/BaseImporter.hh>
#include <OpenMesh/Core/System/omstream.hh>

#include <algorithm>
#include <cctype>
#include <charconv>
#include <cmath>
#include <exception>
#include <fstream>
#include <iostream>
#include <mutex>
#include <new>
#include <sstream>
#include <string>
#include <string_view>
#include <system_error>
#include <vector>

namespace lsnif::scene {
namespace {

using OpenMesh::EdgeHandle;
using OpenMesh::FaceHandle;
using OpenMesh::HalfedgeHandle;
using OpenMesh::Vec2f;
using OpenMesh::Vec3d;
using OpenMesh::Vec3f;
using OpenMesh::Vec3uc;
using OpenMesh::Vec4f;
using OpenMesh::Vec4uc;
using OpenMesh::VertexHandle;
using StatusInfo = OpenMesh::Attributes::StatusInfo;

// Polygons with more corners than this are fan-triangulated (ear clipping is quadratic or
// worse in the corner count); the importer warns when that happens.
constexpr std::size_t kMaxEarClipCorners = 256;

// A BaseImporter that keeps exactly what the reader delivers (see the file comment).
// Only vertices, vertex normals and faces are kept; colours, texture coordinates and
// status bits are ignored. Handles are not trusted: out-of-range ones are recorded (faces)
// or ignored (attributes) and reported by the caller.
class PolygonSoup final : public OpenMesh::IO::BaseImporter {
public:
    std::vector<float> points;                  // 3 per vertex
    std::vector<float> normals;                 // 3 per vertex
    std::vector<std::uint8_t> has_normal;       // per vertex
    std::vector<long long> corners;             // vertex index of every face corner, as read
    std::vector<std::size_t> face_start = {0};  // face f: corners[face_start[f], face_start[f+1])

    VertexHandle add_vertex(const Vec3f& p) override {
        points.insert(points.end(), {p[0], p[1], p[2]});
        normals.insert(normals.end(), {0.0f, 0.0f, 0.0f});
        has_normal.push_back(0);
        return VertexHandle(int(has_normal.size() - 1));
    }
    VertexHandle add_vertex(const Vec3d& p) override {
        return add_vertex(Vec3f(float(p[0]), float(p[1]), float(p[2])));
    }
    VertexHandle add_vertex() override { return add_vertex(Vec3f(0.0f, 0.0f, 0.0f)); }
    FaceHandle add_face(const VHandles& vertices) override {
        for (const VertexHandle& v : vertices) corners.push_back(v.idx());
        face_start.push_back(corners.size());
        return FaceHandle(int(face_start.size() - 2));
    }
    void set_point(VertexHandle v, const Vec3f& p) override {
        if (valid(v)) std::copy_n(p.data(), 3, &points[3 * std::size_t(v.idx())]);
    }
    void set_normal(VertexHandle v, const Vec3f& n) override {
        if (!valid(v)) return;
        std::copy_n(n.data(), 3, &normals[3 * std::size_t(v.idx())]);
        has_normal[std::size_t(v.idx())] = 1;
    }
    void set_normal(VertexHandle v, const Vec3d& n) override {
        set_normal(v, Vec3f(float(n[0]), float(n[1]), float(n[2])));
    }
    std::size_t n_vertices() const override { return has_normal.size(); }
    std::size_t n_faces() const override { return face_start.size() - 1; }
    std::size_t n_edges() const override { return 0; }

    // Everything else is ignored.
    HalfedgeHandle add_edge(VertexHandle, VertexHandle) override { return HalfedgeHandle(); }
    FaceHandle add_face(HalfedgeHandle) override { return FaceHandle(); }
    void add_face_texcoords(FaceHandle, VertexHandle, const std::vector<Vec2f>&) override {}
    void add_face_texcoords(FaceHandle, VertexHandle, const std::vector<Vec3f>&) override {}
    void set_face_texindex(FaceHandle, int) override {}
    void set_halfedge(VertexHandle, HalfedgeHandle) override {}
    void set_color(VertexHandle, const Vec3uc&) override {}
    void set_color(VertexHandle, const Vec4uc&) override {}
    void set_color(VertexHandle, const Vec3f&) override {}
    void set_color(VertexHandle, const Vec4f&) override {}
    void set_texcoord(VertexHandle, const Vec2f&) override {}
    void set_status(VertexHandle, const StatusInfo&) override {}
    void set_next(HalfedgeHandle, HalfedgeHandle) override {}
    void set_face(HalfedgeHandle, FaceHandle) override {}
    void request_face_texcoords2D() override {}
    void set_texcoord(HalfedgeHandle, const Vec2f&) override {}
    void set_texcoord(VertexHandle, const Vec3f&) override {}
    void set_texcoord(HalfedgeHandle, const Vec3f&) override {}
    void set_status(HalfedgeHandle, const StatusInfo&) override {}
    void set_color(EdgeHandle, const Vec3uc&) override {}
    void set_color(EdgeHandle, const Vec4uc&) override {}
    void set_color(EdgeHandle, const Vec3f&) override {}
    void set_color(EdgeHandle, const Vec4f&) override {}
    void set_status(EdgeHandle, const StatusInfo&) override {}
    void set_normal(FaceHandle, const Vec3f&) override {}
    void set_normal(FaceHandle, const Vec3d&) override {}
    void set_color(FaceHandle, const Vec3uc&) override {}
    void set_color(FaceHandle, const Vec4uc&) override {}
    void set_color(FaceHandle, const Vec3f&) override {}
    void set_color(FaceHandle, const Vec4f&) override {}
    void set_status(FaceHandle, const StatusInfo&) override {}
    void add_texture_information(int, std::string) override {}

private:
    bool valid(VertexHandle v) const { return v.idx() >= 0 && std::size_t(v.idx()) < has_normal.size(); }
};

// Captures what OpenMesh's readers report while alive. OpenMesh writes its messages to
// omerr() and omlog(), which forward to std::cerr and std::clog (and some readers write to
// std::cerr directly), so those two streams are pointed at a string buffer for the
// duration and restored afterwards; omout() (std::cout) is muted. (Disconnecting the
// mostreams' targets instead would leak: OpenMesh 9's multiplex_streambuf::disconnect
// never deletes the target it removes.) Process-wide: callers hold log_mutex(), and output
// other threads write to std::cerr / std::clog during a read lands in the warnings.
class LogCapture {
public:
    LogCapture()
        : old_err_(std::cerr.rdbuf(&buffer_)),
          old_log_(std::clog.rdbuf(&buffer_)),
          out_enabled_(omout().is_enabled()) {
        omout().disable();
    }
    ~LogCapture() {
        flush_openmesh();
        std::cerr.rdbuf(old_err_);
        std::clog.rdbuf(old_log_);
        if (out_enabled_) omout().enable();
    }
    LogCapture(const LogCapture&) = delete;
    LogCapture& operator=(const LogCapture&) = delete;

    std::vector<std::string> lines() {
        flush_openmesh();
        std::vector<std::string> out;
        std::istringstream in(buffer_.str());
        for (std::string line; std::getline(in, line);) {
            while (!line.empty() && (line.back() == '\r' || line.back() == ' ')) line.pop_back();
            if (!line.empty()) out.push_back(line);
        }
        return out;
    }

private:
    static void flush_openmesh() {
        omerr().flush();
        omlog().flush();
        omout().flush();
    }
    std::stringbuf buffer_;
    std::streambuf* old_err_;
    std::streambuf* old_log_;
    bool out_enabled_;
};

std::mutex& log_mutex() {
    static std::mutex m;
    return m;
}

std::string read_head(const std::filesystem::path& path, std::size_t limit) {
    std::ifstream in(path, std::ios::binary);
    std::string head(limit, '\0');
    in.read(head.data(), std::streamsize(limit));
    head.resize(std::size_t(std::max<std::streamsize>(in.gcount(), 0)));
    return head;
}

bool parse_count(const std::string& token, unsigned long long& out) {
    if (token.empty() || token.size() > 20) return false;
    unsigned long long v = 0;
    for (const char c : token) {
        if (c < '0' || c > '9') return false;
        const unsigned long long next = v * 10 + unsigned(c - '0');
        if (next / 10 != v) return false;
        v = next;
    }
    out = v;
    return true;
}

// OFF: "[ST][C][N][4][n]OFF [BINARY]", then "nv nf ne" ('#' comments anywhere). Every
// ASCII vertex takes at least 6 bytes ("0 0 0\n"), every face at least 2. Returns "" or
// the problem. Headers it does not understand are left to OpenMesh.
std::string check_off_header(const std::string& head, std::uintmax_t size) {
    std::vector<std::string> tokens;
    std::istringstream in(head);
    for (std::string line; tokens.size() < 4 && std::getline(in, line);) {
        if (const auto hash = line.find('#'); hash != std::string::npos) line.resize(hash);
        std::istringstream ls(line);
        for (std::string t; tokens.size() < 4 && ls >> t;) tokens.push_back(t);
    }
    if (tokens.empty()) return {};
    std::size_t i = 0;
    const std::string& keyword = tokens[0];
    if (keyword.size() >= 3 && keyword.compare(keyword.size() - 3, 3, "OFF") == 0) {
        // nOFF and 4OFF have other layouts, BINARY files other sizes: not checked.
        if (keyword.find('n') != std::string::npos || keyword.find('4') != std::string::npos) {
            return {};
        }
        ++i;
        if (i < tokens.size() && tokens[i] == "BINARY") return {};
    }
    unsigned long long nv = 0, nf = 0;
    if (i + 1 >= tokens.size() || !parse_count(tokens[i], nv) || !parse_count(tokens[i + 1], nf)) {
        return {};
    }
    if (nv > size / 6 || nf > size / 2 || nv * 6 + nf * 2 > size + 2) {
        return "the OFF header declares " + std::to_string(nv) + " vertices and " + std::to_string(nf) +
               " faces, more than a file of " + std::to_string(size) + " bytes can hold";
    }
    return {};
}

// A PLY property as check_ply_body walks it: a scalar of `bytes`, or a list whose length is
// an integer of `count_bytes` followed by that many values of `bytes` each. `declaration` is
// its header line's words joined by single spaces ("property list uchar int vertex_indices").
struct PlyProperty {
    bool list = false;
    int count_bytes = 0, bytes = 0;
    bool count_signed = false, count_integer = true;
    std::string declaration;
};
struct PlyElement {
    std::string name;
    unsigned long long count = 0;
    std::vector<PlyProperty> properties;
};
// What a checked PLY header declares: its format, its elements in file order, and where the
// body starts (the byte after the end_header line).
struct PlyLayout {
    std::string format;
    std::vector<PlyElement> elements;
    std::size_t body = 0;
};

// A PLY type's size in bytes, and whether it is an integer and signed; 0 for no PLY type.
struct PlyType {
    int bytes = 0;
    bool integer = false, is_signed = false;
};
PlyType ply_type(const std::string& t) {
    if (t == "char" || t == "int8") return {1, true, true};
    if (t == "uchar" || t == "uint8") return {1, true, false};
    if (t == "short" || t == "int16") return {2, true, true};
    if (t == "ushort" || t == "uint16") return {2, true, false};
    if (t == "int" || t == "int32") return {4, true, true};
    if (t == "uint" || t == "uint32") return {4, true, false};
    if (t == "float" || t == "float32") return {4, false, true};
    if (t == "double" || t == "float64") return {8, false, true};
    return {};
}

// PLY: the header must follow the grammar below, and every "element NAME COUNT" must fit
// in the file (at least one byte per element). Fills `layout`. Returns "" or the problem.
//   ply / format (ascii|binary_little_endian|binary_big_endian) 1.0 / element NAME COUNT /
//   property TYPE NAME / property list TYPE TYPE NAME / end_header
// The format line comes before any element. Other lines (comment, obj_info, and the
// unprefixed notes some exporters write, e.g. Blender's "Created by ...") are skipped,
// wherever they are and whatever words they hold: OpenMesh never sees them, it reads the
// header ply_header_for_openmesh writes from `layout`. Control bytes are not text.
std::string check_ply_header(const std::string& head, std::uintmax_t size, PlyLayout& layout) {
    auto is_type = [](const std::string& t) { return ply_type(t).bytes != 0; };
    std::size_t pos = 0, line_no = 0;
    bool have_format = false;
    while (true) {
        const std::size_t nl = head.find('\n', pos);
        if (nl == std::string::npos)
            return "the PLY header has no end_header line within its first " + std::to_string(head.size()) +
                   " bytes";
        std::string line = head.substr(pos, nl - pos);
        pos = nl + 1;
        ++line_no;
        if (!line.empty() && line.back() == '\r') line.pop_back();
        for (const char c : line)
            if ((c >= 0 && c < 0x20 && c != '\t') || c == 0x7f)
                return "PLY header line " + std::to_string(line_no) + " has a control byte";
        std::istringstream ls(line);
        std::vector<std::string> w;
        for (std::string t; ls >> t;) w.push_back(t);
        const auto bad = [&](const std::string& what) {
            return "PLY header line " + std::to_string(line_no) + ": " + what;
        };
        if (line_no == 1) {
            if (w.size() != 1 || w[0] != "ply") return bad("the file must start with a line 'ply'");
            continue;
        }
        if (w.empty()) continue;
        const bool keyword =
            w[0] == "format" || w[0] == "element" || w[0] == "property" || w[0] == "end_header";
        if (!keyword) continue;
        if (w[0] == "format") {
            if (w.size() != 3 ||
                (w[1] != "ascii" && w[1] != "binary_little_endian" && w[1] != "binary_big_endian") ||
                w[2] != "1.0")
                return bad("expected 'format ascii|binary_little_endian|binary_big_endian 1.0'");
            if (have_format) return bad("a second format line");
            have_format = true;
            layout.format = w[1];
            continue;
        }
        if (!have_format) return bad("'" + w[0] + "' before the format line");
        if (w[0] == "end_header") {
            if (w.size() != 1) return bad("text after end_header");
            layout.body = pos;
            return {};
        }
        if (w[0] == "element") {
            unsigned long long count = 0;
            if (w.size() != 3 || !parse_count(w[2], count)) return bad("expected 'element NAME COUNT'");
            if (count > size)
                return "the PLY header declares " + std::to_string(count) + " '" + w[1] +
                       "' elements, more than a file of " + std::to_string(size) + " bytes can hold";
            // OpenMesh reads the count as an unsigned int.
            if (count > 0xffffffffull) return bad("more than 2^32 - 1 '" + w[1] + "' elements");
            layout.elements.push_back({w[1], count, {}});
            continue;
        }
        if (layout.elements.empty()) return bad("property before any element");
        const bool ok = (w.size() == 3 && is_type(w[1])) ||
                        (w.size() == 5 && w[1] == "list" && is_type(w[2]) && is_type(w[3]));
        if (!ok) return bad("expected 'property TYPE NAME' or 'property list TYPE TYPE NAME'");
        PlyProperty prop;
        if (w.size() == 3) {
            prop.bytes = ply_type(w[1]).bytes;
        } else {
            const PlyType count = ply_type(w[2]);
            prop = {true, count.bytes, ply_type(w[3]).bytes, count.is_signed, count.integer, {}};
        }
        for (const std::string& word : w) {
            if (!prop.declaration.empty()) prop.declaration += ' ';
            prop.declaration += word;
        }
        layout.elements.back().properties.push_back(std::move(prop));
    }
}

// The header OpenMesh reads in place of the file's: the checked layout only, one statement
// per line, "\n" line ends, no comments. OpenMesh 9's PLY reader takes the header word by
// word (every word of a line it does not know is a keyword to it, and the three words after
// 'ply' are the format line whatever they are), and it finds a binary body 12 bytes (14
// after "\r\n") past the end of the word before 'end_header': a comment line or trailing
// blanks before end_header shifted the body it read (garbage vertices, no error). On this
// header its reading and ours agree. Never longer than the header it replaces (the same
// words with single blanks, counts without leading zeros).
std::string ply_header_for_openmesh(const PlyLayout& layout) {
    std::string h = "ply\nformat " + layout.format + " 1.0\n";
    for (const PlyElement& e : layout.elements) {
        h += "element " + e.name + " " + std::to_string(e.count) + "\n";
        for (const PlyProperty& p : e.properties) h += p.declaration + "\n";
    }
    return h + "end_header\n";
}

// PLY body: every list's length must be a count the rest of the file can hold (ASCII: a
// run of digits, each value at least two bytes with its separator; binary: a non-negative
// integer, the values' bytes within the file). OpenMesh reserves and value-initializes a list
// of the length it reads, so an ASCII length beyond its integer type, or a huge binary one,
// made it allocate gigabytes (found by fuzz_import). A body that ends early is left to
// OpenMesh, as before. `text` is the whole file. Returns "" or the problem.
std::string check_ply_body(const std::string& text, const PlyLayout& layout) {
    const auto too_long = [&](const PlyElement& e, unsigned long long i, const std::string& length,
                              std::size_t left) {
        return "PLY element '" + e.name + "' " + std::to_string(i) + " has a list of " + length +
               " values, more than the remaining " + std::to_string(left) + " bytes can hold";
    };
    std::size_t pos = layout.body;
    if (layout.format == "ascii") {
        const auto token = [&](std::string& out) {
            while (pos < text.size() && std::isspace(static_cast<unsigned char>(text[pos]))) ++pos;
            const std::size_t begin = pos;
            while (pos < text.size() && !std::isspace(static_cast<unsigned char>(text[pos]))) ++pos;
            out.assign(text, begin, pos - begin);
            return pos > begin;
        };
        std::string t;
        for (const PlyElement& e : layout.elements)
            for (unsigned long long i = 0; i < e.count; ++i)
                for (const PlyProperty& p : e.properties) {
                    if (!token(t)) return {};
                    if (!p.list) continue;
                    unsigned long long n = 0;
                    const std::size_t left = text.size() - pos;
                    if (!parse_count(t, n)) {
                        if (t.size() > 24) t = t.substr(0, 20) + "...";
                        return "PLY element '" + e.name + "' " + std::to_string(i) + " has a list length '" +
                               t + "', not a count";
                    }
                    if (n > (left + 1) / 2) return too_long(e, i, std::to_string(n), left);
                    for (unsigned long long k = 0; k < n; ++k)
                        if (!token(t)) return {};
                }
        return {};
    }
    const bool big_endian = layout.format == "binary_big_endian";
    for (const PlyElement& e : layout.elements)
        for (unsigned long long i = 0; i < e.count; ++i)
            for (const PlyProperty& p : e.properties) {
                if (!p.list) {
                    if (text.size() - pos < std::size_t(p.bytes)) return {};
                    pos += std::size_t(p.bytes);
                    continue;
                }
                if (!p.count_integer)
                    return "PLY element '" + e.name + "' has a list whose length is not an integer type";
                if (text.size() - pos < std::size_t(p.count_bytes)) return {};
                unsigned long long n = 0;
                for (int b = 0; b < p.count_bytes; ++b) {
                    const int at = big_endian ? b : p.count_bytes - 1 - b;
                    n = n << 8 | static_cast<unsigned char>(text[pos + std::size_t(at)]);
                }
                pos += std::size_t(p.count_bytes);
                const bool negative = p.count_signed && (n >> (8 * p.count_bytes - 1)) != 0;
                const std::size_t left = text.size() - pos;
                if (negative || n > left / std::size_t(p.bytes))
                    return too_long(e, i, negative ? "a negative number of" : std::to_string(n), left);
                pos += std::size_t(n) * std::size_t(p.bytes);
            }
    return {};
}

// One OBJ face corner: a vertex index, then optionally "/" and a texture index and "/" and a
// normal index, where the texture or normal index may be empty ("1/", "1//", "1/2/": what
// Blender, assimp and tinyobjloader read as the indices that are there; printer-bed models
// of 3D-printing software are written "f 1/ 2/ 3/"). Indices are non-zero integers
// (negative = relative); `is_index` says which are.
template <class IsIndex>
bool obj_corner(std::string_view corner, const IsIndex& is_index) {
    const std::size_t s1 = corner.find('/');
    if (!is_index(corner.substr(0, s1))) return false;
    if (s1 == std::string_view::npos) return true;
    const std::string_view rest = corner.substr(s1 + 1);
    const std::size_t s2 = rest.find('/');
    const std::string_view vt = rest.substr(0, s2);
    if (!vt.empty() && !is_index(vt)) return false;
    if (s2 == std::string_view::npos) return true;
    const std::string_view vn = rest.substr(s2 + 1);
    return vn.empty() || is_index(vn);
}

// Whitespace between tokens within a line, as an istream in the C locale (OpenMesh's
// readers) sees it.
bool is_space(char c) {
    return c == ' ' || c == '\t' || c == '\r' || c == '\v' || c == '\f';
}

// OBJ: every face ("f") line must be a list of corners (obj_corner). Debian's OpenMesh 9 is
// built with assertions, and its OBJ reader aborts the process on a corner without a vertex
// index (e.g. "f /1 2 3"; found by fuzz_import), so such files are rejected here with the
// line number. Returns "" or the problem.
std::string check_obj_faces(const std::string& text) {
    auto is_index = [](std::string_view t) {
        if (!t.empty() && t[0] == '-') t.remove_prefix(1);
        if (t.empty() || t.size() > 19) return false;
        bool nonzero = false;
        for (const char c : t) {
            if (c < '0' || c > '9') return false;
            nonzero = nonzero || c != '0';
        }
        return nonzero;
    };
    std::size_t pos = 0, line_no = 0;
    while (pos < text.size()) {
        std::size_t end = text.find('\n', pos);
        if (end == std::string::npos) end = text.size();
        std::string_view line = std::string_view(text).substr(pos, end - pos);
        pos = end + 1;
        ++line_no;
        std::size_t i = 0;
        while (i < line.size() && is_space(line[i])) ++i;
        if (line.size() < i + 2 || line[i] != 'f' || !is_space(line[i + 1])) continue;
        line.remove_prefix(i + 2);
        if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
        // A line continued with a backslash is joined by OpenMesh; keep it simple: refuse.
        if (!line.empty() && line.back() == '\\')
            return "line " + std::to_string(line_no) + ": continued face line";
        std::size_t corners = 0, k = 0;
        while (k < line.size()) {
            while (k < line.size() && is_space(line[k])) ++k;
            const std::size_t start = k;
            while (k < line.size() && !is_space(line[k])) ++k;
            if (k == start) break;
            const std::string_view corner = line.substr(start, k - start);
            if (!obj_corner(corner, is_index))
                return "line " + std::to_string(line_no) + ": face corner '" +
                       std::string(corner.substr(0, 40)) +
                       "' is not v, v/vt, v//vn or v/vt/vn (a missing vt or vn may be empty) with non-zero "
                       "indices";
            ++corners;
        }
        if (corners == 0) return "line " + std::to_string(line_no) + ": face without corners";
    }
    return {};
}

// Splits `line` at whitespace into `out` (views into line).
void split(std::string_view line, std::vector<std::string_view>& out) {
    out.clear();
    std::size_t i = 0;
    while (i < line.size()) {
        while (i < line.size() && is_space(line[i])) ++i;
        const std::size_t start = i;
        while (i < line.size() && !is_space(line[i])) ++i;
        if (i > start) out.push_back(line.substr(start, i - start));
    }
}

bool parse_float(std::string_view t, float& out) {
    if (!t.empty() && t[0] == '+') t.remove_prefix(1);
    double d = 0.0;  // parsed in double, then rounded once to float
    const auto [end, ec] = std::from_chars(t.data(), t.data() + t.size(), d);
    if (ec != std::errc() || end != t.data() + t.size()) return false;
    out = float(d);
    return true;
}

bool parse_int(std::string_view t, long long& out) {
    if (!t.empty() && t[0] == '+') t.remove_prefix(1);
    const auto [end, ec] = std::from_chars(t.data(), t.data() + t.size(), out);
    return ec == std::errc() && end == t.data() + t.size();
}

// The lines of an ASCII OFF text, read one non-blank line at a time.
class OffLines {
public:
    explicit OffLines(const std::string& text) : text_(text) {}

    // Moves to the next non-blank line, '#' comment stripped, and splits it into tok;
    // false at the end of the text.
    bool next() {
        while (pos_ < text_.size()) {
            std::size_t end = text_.find('\n', pos_);
            if (end == std::string::npos) end = text_.size();
            std::string_view line = std::string_view(text_).substr(pos_, end - pos_);
            pos_ = end + 1;
            ++line_no_;
            if (const auto hash = line.find('#'); hash != std::string_view::npos) line = line.substr(0, hash);
            split(line, tok);
            if (!tok.empty()) return true;
        }
        return false;
    }
    // `what`, prefixed with the current line's number.
    std::string at(const std::string& what) const { return "line " + std::to_string(line_no_) + ": " + what; }

    std::vector<std::string_view> tok;  // the current line's tokens (views into the text)

private:
    const std::string& text_;
    std::size_t pos_ = 0, line_no_ = 0;
};

struct OffHeader {
    bool binary = false;       // "OFF BINARY": nothing else was read
    bool has_normals = false;  // the keyword has N: vertex lines carry a normal
    long long nv = 0, nf = 0;  // vertex and face counts, >= 0
};

// The optional [ST][C][N]OFF keyword and the "nv nf [ne]" counts, from the first lines of
// `in`. Returns "" or the problem; stops right after the keyword for "OFF BINARY".
std::string read_off_header(OffLines& in, OffHeader& h) {
    if (!in.next()) return "no OFF header";
    std::size_t first = 0;
    const std::string_view keyword = in.tok[0];
    if (keyword.size() >= 3 && keyword.substr(keyword.size() - 3) == "OFF") {
        const std::string_view prefix = keyword.substr(0, keyword.size() - 3);
        if (prefix.find_first_not_of("STCN") != std::string_view::npos) {
            return in.at("OFF variant '" + std::string(keyword) +
                         "' is not supported (only 3D [ST][C][N]OFF)");
        }
        h.has_normals = prefix.find('N') != std::string_view::npos;
        if (in.tok.size() > 1 && in.tok[1] == "BINARY") {
            h.binary = true;
            return {};
        }
        first = 1;
        if (in.tok.size() == 1) {
            if (!in.next()) return "no vertex/face counts after the OFF keyword";
            first = 0;
        }
    }
    const auto& tok = in.tok;
    if (tok.size() < first + 2 || !parse_int(tok[first], h.nv) || !parse_int(tok[first + 1], h.nf) ||
        h.nv < 0 || h.nf < 0) {
        return in.at("expected the vertex and face counts \"nv nf [ne]\"");
    }
    return {};
}

// The h.nv vertex lines that follow the header, into `soup`; `text_size` bounds what is
// reserved. Returns "" or the problem.
std::string read_off_vertices(OffLines& in, const OffHeader& h, std::size_t text_size, PolygonSoup& soup) {
    const std::size_t values = h.has_normals ? 6 : 3;
    // Every vertex line takes at least 6 bytes: never reserve more than the text can hold.
    const std::size_t reserve = std::min<std::size_t>(std::size_t(h.nv), text_size / 6);
    soup.points.reserve(3 * reserve);
    soup.normals.reserve(3 * reserve);
    soup.has_normal.reserve(reserve);
    for (long long v = 0; v < h.nv; ++v) {
        if (!in.next()) {
            return "the file ends after " + std::to_string(v) + " of " + std::to_string(h.nv) + " vertices";
        }
        float x[6] = {};
        if (in.tok.size() < values) {
            return in.at("vertex " + std::to_string(v) + " has " + std::to_string(in.tok.size()) +
                         " values, " + std::to_string(values) + " expected");
        }
        for (std::size_t k = 0; k < values; ++k) {
            if (!parse_float(in.tok[k], x[k])) {
                return in.at("vertex " + std::to_string(v) + ": '" + std::string(in.tok[k]) +
                             "' is not a number");
            }
        }
        const VertexHandle vh = soup.add_vertex(Vec3f(x[0], x[1], x[2]));
        if (h.has_normals) soup.set_normal(vh, Vec3f(x[3], x[4], x[5]));
    }
    return {};
}

// The `nf` face lines that follow the vertices, into `soup`; indices out of int range are
// recorded as -1 (the caller range-checks them all). Returns "" or the problem.
std::string read_off_faces(OffLines& in, long long nf, PolygonSoup& soup) {
    const auto& tok = in.tok;
    OpenMesh::IO::BaseImporter::VHandles face;
    for (long long f = 0; f < nf; ++f) {
        if (!in.next())
            return "the file ends after " + std::to_string(f) + " of " + std::to_string(nf) + " faces";
        long long k = 0;
        if (!parse_int(tok[0], k) || k < 0 || std::size_t(k) > tok.size() - 1) {
            return in.at("face " + std::to_string(f) +
                         ": expected a corner count and that many vertex indices");
        }
        face.clear();
        for (long long c = 1; c <= k; ++c) {
            long long idx = 0;
            if (!parse_int(tok[std::size_t(c)], idx)) {
                return in.at("face " + std::to_string(f) + ": '" + std::string(tok[std::size_t(c)]) +
                             "' is not a vertex index");
            }
            face.push_back(VertexHandle(idx >= 0 && idx <= 0x7fffffffLL ? int(idx) : -1));
        }
        soup.add_face(face);
    }
    return {};
}

// ASCII OFF (Geomview's format, as written by CGAL and most tools):
//   [ST][C][N]OFF            optional keyword: texture coordinates, colours, normals
//   nv nf [ne]               may stand on the keyword's line
//   nv vertex lines          x y z [nx ny nz when N] [colour / texture values: ignored]
//   nf face lines            k i_1 ... i_k [colour values: ignored]
// '#' starts a comment to the end of its line; blank lines are skipped; anything after the
// faces is ignored. Fills `soup` (indices are range-checked by the caller). Returns "" or
// the problem with its line number; sets `binary` (and reads nothing) for "OFF BINARY".
std::string read_ascii_off(const std::string& text, PolygonSoup& soup, bool& binary) {
    OffLines in(text);
    OffHeader h;
    const std::string problem = read_off_header(in, h);
    binary = h.binary;
    if (!problem.empty() || binary) return problem;
    if (std::string p = read_off_vertices(in, h, text.size(), soup); !p.empty()) return p;
    return read_off_faces(in, h.nf, soup);
}

double cross2(const double* o, const double* a, const double* b) {
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]);
}

// Appends the fan of triangles (ring[0], ring[k], ring[k + 1]) to `out`.
void fan(const std::vector<std::uint32_t>& ring, std::vector<std::uint32_t>& out) {
    for (std::size_t k = 1; k + 1 < ring.size(); ++k) {
        out.insert(out.end(), {ring[0], ring[k], ring[k + 1]});
    }
}

// Adds to `normal` the Newell normal of polygon `poly` (n corner indices into `pos`),
// unnormalized: the sum over edges of (y_i - y_j)(z_i + z_j), ...
void newell_normal(const std::vector<float>& pos, const std::uint32_t* poly, std::size_t n,
                   double (&normal)[3]) {
    for (std::size_t i = 0; i < n; ++i) {
        const float* a = &pos[3 * std::size_t(poly[i])];
        const float* b = &pos[3 * std::size_t(poly[(i + 1) % n])];
        normal[0] += (double(a[1]) - b[1]) * (double(a[2]) + b[2]);
        normal[1] += (double(a[2]) - b[2]) * (double(a[0]) + b[0]);
        normal[2] += (double(a[0]) - b[0]) * (double(a[1]) + b[1]);
    }
}

// Ear clipping of `ring` (corner vertex indices) whose corners are at xy[2 i], xy[2 i + 1],
// counter-clockwise. Returns false, after fan-triangulating what is left, when no ear is
// found (self-intersecting or numerically degenerate remainder).
bool ear_clip(const std::vector<double>& xy, const std::vector<std::uint32_t>& ring,
              std::vector<std::uint32_t>& out) {
    std::vector<std::size_t> left(ring.size());
    for (std::size_t i = 0; i < ring.size(); ++i) left[i] = i;
    while (left.size() > 3) {
        const std::size_t m = left.size();
        bool clipped = false;
        for (std::size_t k = 0; k < m && !clipped; ++k) {
            const std::size_t ia = left[(k + m - 1) % m], ib = left[k], ic = left[(k + 1) % m];
            const double *a = &xy[2 * ia], *b = &xy[2 * ib], *c = &xy[2 * ic];
            if (!(cross2(a, b, c) > 0.0)) continue;  // reflex or collinear corner: no ear
            bool empty = true;
            for (std::size_t j = 0; j < m && empty; ++j) {
                const std::size_t ip = left[j];
                if (ip == ia || ip == ib || ip == ic) continue;
                const double* p = &xy[2 * ip];
                if (cross2(a, b, p) >= 0.0 && cross2(b, c, p) >= 0.0 && cross2(c, a, p) >= 0.0) {
                    empty = false;
                }
            }
            if (!empty) continue;
            out.insert(out.end(), {ring[ia], ring[ib], ring[ic]});
            left.erase(left.begin() + std::ptrdiff_t(k));
            clipped = true;
        }
        if (!clipped) {
            std::vector<std::uint32_t> rest;
            for (const std::size_t i : left) rest.push_back(ring[i]);
            fan(rest, out);
            return false;
        }
    }
    out.insert(out.end(), {ring[left[0]], ring[left[1]], ring[left[2]]});
    return true;
}

// Triangulates one polygon (corner vertex indices, n >= 3, all valid) into `out`, keeping
// its orientation. Ear clipping in the plane of the Newell normal; polygons that are
// degenerate, self-intersecting (no ear left) or larger than kMaxEarClipCorners fall back
// to a fan around the first corner. Returns false when the fan fallback was used for a
// polygon that is not degenerate.
bool triangulate(const std::vector<float>& pos, const std::uint32_t* poly, std::size_t n,
                 std::vector<std::uint32_t>& out) {
    std::vector<std::uint32_t> ring(poly, poly + n);
    if (n == 3) {
        fan(ring, out);
        return true;
    }
    double normal[3] = {0, 0, 0};
    newell_normal(pos, poly, n, normal);
    int axis = 0;
    for (int a = 1; a < 3; ++a) {
        if (std::fabs(normal[a]) > std::fabs(normal[axis])) axis = a;
    }
    if (!(std::fabs(normal[axis]) > 0.0)) {  // degenerate polygon: any triangulation is
        fan(ring, out);                      // equally degenerate
        return true;
    }
    if (n > kMaxEarClipCorners) {
        fan(ring, out);
        return false;
    }
    // Project along `axis`, ordering the two kept coordinates so the polygon is
    // counter-clockwise in 2D.
    int u = (axis + 1) % 3, v = (axis + 2) % 3;
    if (normal[axis] < 0) std::swap(u, v);
    std::vector<double> xy(2 * n);
    for (std::size_t i = 0; i < n; ++i) {
        const float* p = &pos[3 * std::size_t(poly[i])];
        xy[2 * i] = p[u];
        xy[2 * i + 1] = p[v];
    }
    return ear_clip(xy, ring, out);
}

ImportResult failure(const std::string& file, const std::string& what) {
    return {{}, file + ": " + what};
}

ImportResult failure(const std::string& file, const std::string& what, detail::WarningSink& warnings) {
    ImportResult r = failure(file, what);
    warnings.finish(r.scene.warnings);
    return r;
}

// The checks made before any reader sees the file `path` of extension `ext`: a supported
// format, a non-empty readable regular file (its byte count into `size`), and the OBJ face
// lines or OFF header that would crash or exhaust OpenMesh (a PLY file's are read_ply's).
// Returns "" or the problem.
std::string check_mesh_file(const std::filesystem::path& path, const std::string& ext, std::uintmax_t& size) {
    if (ext != ".obj" && ext != ".ply" && ext != ".off" && ext != ".stl") {
        return "unsupported mesh format '" + ext + "' (supported: .obj .ply .off .stl)";
    }
    if (const std::string problem = detail::regular_file_size(path, size); !problem.empty()) return problem;
    if (size == 0) return "file is empty";
    {
        std::ifstream probe(path, std::ios::binary);
        if (!probe) return "cannot open for reading";
    }
    if (ext == ".obj") {
        const std::string text = read_head(path, static_cast<std::size_t>(size));
        if (const std::string problem = check_obj_faces(text); !problem.empty()) return problem;
    }
    if (ext == ".off") return check_off_header(read_head(path, 1 << 16), size);
    return {};
}

// Runs one OpenMesh read (`read(options)` returns its success) with OpenMesh's log captured:
// the log lines become warnings, or the error's detail when the read fails. Returns "" or the
// problem.
template <class Read>
std::string read_through_openmesh(const std::string& ext, detail::WarningSink& warnings, const Read& read) {
    std::lock_guard<std::mutex> lock(log_mutex());
    LogCapture capture;
    OpenMesh::IO::Options options = OpenMesh::IO::Options::VertexNormal;
    const bool read_ok = read(options);
    std::vector<std::string> log = capture.lines();
    if (!read_ok) {
        std::string why;
        for (std::size_t i = 0; i < log.size() && i < 3; ++i) why += (i ? "; " : "") + log[i];
        return "OpenMesh could not read it as " + ext.substr(1) +
               (why.empty() ? std::string() : " (" + why + ")");
    }
    for (std::string& line : log) warnings.add("OpenMesh: " + line);
    return {};
}

// Reads the PLY file `path` of `size` bytes into `soup`: its header is checked first
// (check_ply_header on the first 64 KiB), then the whole file's body (check_ply_body), then
// OpenMesh reads the body under the header ply_header_for_openmesh writes, from memory.
// Returns "" or the problem.
std::string read_ply(const std::filesystem::path& path, std::uintmax_t size, PolygonSoup& soup,
                     detail::WarningSink& warnings) {
    const std::string head = read_head(path, 1 << 16);
    PlyLayout layout;
    if (const std::string problem = check_ply_header(head, size, layout); !problem.empty()) return problem;
    std::string text = read_head(path, static_cast<std::size_t>(size));
    if (text.size() != size || text.compare(0, layout.body, head, 0, layout.body) != 0)
        return "the file changed while it was read";
    if (const std::string problem = check_ply_body(text, layout); !problem.empty()) return problem;
    text.replace(0, layout.body, ply_header_for_openmesh(layout));
    std::istringstream in(std::move(text), std::ios::in | std::ios::binary);
    return read_through_openmesh(".ply", warnings, [&](OpenMesh::IO::Options& options) {
        return OpenMesh::IO::IOManager().read(in, "ply", soup, options);
    });
}

// Reads the checked file `path` (`name` for OpenMesh, which picks its reader by name) of
// `size` bytes into `soup`: ASCII OFF with read_ascii_off (binary OFF is an error), PLY with
// read_ply, OBJ and STL with OpenMesh, whose log lines become warnings. Returns "" or the
// problem.
std::string read_soup(const std::filesystem::path& path, const std::string& name, const std::string& ext,
                      std::uintmax_t size, PolygonSoup& soup, detail::WarningSink& warnings) {
    if (ext == ".off") {
        std::string text(static_cast<std::size_t>(size), '\0');
        std::ifstream in(path, std::ios::binary);
        in.read(text.data(), std::streamsize(text.size()));
        if (std::size_t(in.gcount()) != text.size()) return "read error";
        bool binary = false;
        if (const std::string problem = read_ascii_off(text, soup, binary); !problem.empty()) return problem;
        if (!binary) return {};
        return "binary OFF ('OFF BINARY') is not supported: convert it to ASCII OFF, PLY, OBJ or glTF";
    }
    if (ext == ".ply") return read_ply(path, size, soup, warnings);
    return read_through_openmesh(ext, warnings, [&](OpenMesh::IO::Options& options) {
        return OpenMesh::IO::IOManager().read(name, soup, options);
    });
}

// Checks that `soup` has 1 .. 2^32 - 1 vertices, all finite. Returns "" or the problem.
std::string check_vertices(const PolygonSoup& soup) {
    const std::size_t nv = soup.n_vertices();
    if (nv == 0) return "the file has no vertices";
    if (nv > 0xffffffffull) return "more than 2^32 - 1 vertices";
    for (std::size_t v = 0; v < nv; ++v) {
        const float* p = &soup.points[3 * v];
        if (!std::isfinite(p[0]) || !std::isfinite(p[1]) || !std::isfinite(p[2])) {
            return "vertex " + std::to_string(v) + " is (" + std::to_string(p[0]) + ", " +
                   std::to_string(p[1]) + ", " + std::to_string(p[2]) + "), not finite";
        }
    }
    return {};
}

// Triangulates every face of `soup` (checked by check_vertices) into mesh.indices, skipping
// faces of fewer than 3 corners; warns about those and about fan-triangulated polygons.
// Returns "" or the problem: a corner index out of range, or no triangle at all.
std::string triangulate_faces(const PolygonSoup& soup, Mesh& mesh, detail::WarningSink& warnings) {
    const std::size_t nv = soup.n_vertices(), nf = soup.n_faces();
    std::size_t short_faces = 0, fanned = 0;
    std::vector<std::uint32_t> poly;
    for (std::size_t f = 0; f < nf; ++f) {
        const std::size_t begin = soup.face_start[f], end = soup.face_start[f + 1];
        poly.clear();
        for (std::size_t c = begin; c < end; ++c) {
            const long long idx = soup.corners[c];
            if (idx < 0 || std::size_t(idx) >= nv) {
                return "face " + std::to_string(f) + " refers to vertex " + std::to_string(idx) +
                       ", but the file has " + std::to_string(nv) + " vertices";
            }
            poly.push_back(std::uint32_t(idx));
        }
        if (poly.size() < 3) {
            ++short_faces;
            continue;
        }
        if (!triangulate(soup.points, poly.data(), poly.size(), mesh.indices)) ++fanned;
    }
    if (short_faces != 0) {
        warnings.add(std::to_string(short_faces) + " faces with fewer than 3 corners skipped");
    }
    if (fanned != 0) {
        warnings.add(std::to_string(fanned) +
                     " polygons could not be ear-clipped (self-intersecting or more than " +
                     std::to_string(kMaxEarClipCorners) + " corners); fan-triangulated");
    }
    if (mesh.indices.empty()) {
        return "no triangles (" + std::to_string(nf) + " faces, " + std::to_string(short_faces) +
               " of them with fewer than 3 corners)";
    }
    return {};
}

ImportResult import_mesh_file_impl(const std::filesystem::path& path, const std::string& name) {
    const std::string ext = detail::lower_extension(name);
    std::uintmax_t size = 0;
    if (const std::string problem = check_mesh_file(path, ext, size); !problem.empty())
        return failure(name, problem);
    PolygonSoup soup;
    detail::WarningSink warnings;
    if (const std::string problem = read_soup(path, name, ext, size, soup, warnings); !problem.empty())
        return failure(name, problem);
    if (const std::string problem = check_vertices(soup); !problem.empty())
        return failure(name, problem, warnings);

    Mesh mesh;
    mesh.name = path.stem().string();
    if (const std::string problem = triangulate_faces(soup, mesh, warnings); !problem.empty())
        return failure(name, problem, warnings);
    mesh.positions = std::move(soup.points);
    mesh.normals = std::move(soup.normals);
    mesh.triangle_materials.assign(mesh.triangle_count(), 0);
    detail::finalize_normals(mesh, soup.has_normal, "mesh" + detail::quote_name(mesh.name), warnings);

    ImportResult result;
    result.scene.materials = {"default"};
    Instance instance;
    instance.mesh = 0;
    instance.node_name = mesh.name;
    result.scene.meshes.push_back(std::move(mesh));
    result.scene.instances.push_back(std::move(instance));
    warnings.finish(result.scene.warnings);
    return result;
}

}  // namespace

ImportResult import_mesh_file(const std::filesystem::path& path) {
    std::string name;
    try {
        name = path.string();
        return import_mesh_file_impl(path, name);
    } catch (const std::bad_alloc&) {
        return failure(name, "out of memory while importing");
    } catch (const std::exception& e) {
        return failure(name, std::string("import failed: ") + e.what());
    } catch (...) {
        return failure(name, "import failed (unknown exception)");
    }
}

}  // namespace lsnif::scene
