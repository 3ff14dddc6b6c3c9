// The `lsnif` Python module: the reader's C API (lsnif.h) for NumPy. Only the public C API is
// used, so the module works with the shared reader a distribution ships as with the static
// one. Arrays are copied out of the handle (NumPy owns them); rays are copied into one
// contiguous lsnif_ray buffer and traced with the GIL released, so Python threads trace in
// parallel.
#include <lsnif/lsnif.h>
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>

#include <cstring>
#include <initializer_list>
#include <limits>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

namespace py = pybind11;

namespace {

// Raised for every non-OK status; Python sees lsnif.Error (a RuntimeError).
struct Error : std::runtime_error {
    using std::runtime_error::runtime_error;
};

void check(lsnif_status status, const std::string& what) {
    if (status != LSNIF_OK) throw Error(what + ": " + lsnif_status_string(status));
}

using FloatArray = py::array_t<float, py::array::c_style | py::array::forcecast>;

// The rays of a call: origins and directions (N, 3), tmin and tmax numbers or (N,).
std::vector<lsnif_ray> make_rays(const FloatArray& origins, const FloatArray& directions,
                                 const py::object& tmin, const py::object& tmax) {
    if (origins.ndim() != 2 || origins.shape(1) != 3) throw py::value_error("origins must have shape (N, 3)");
    if (directions.ndim() != 2 || directions.shape(1) != 3 || directions.shape(0) != origins.shape(0))
        throw py::value_error("directions must have the shape of origins, (N, 3)");
    const auto n = std::size_t(origins.shape(0));
    const auto bound = [n](const py::object& v, const char* name) {
        FloatArray a = FloatArray::ensure(v);
        if (!a) throw py::value_error(std::string(name) + " must be a number or an array of N numbers");
        if (a.ndim() == 0) return std::vector<float>(n, *a.data());
        if (a.ndim() != 1 || std::size_t(a.shape(0)) != n)
            throw py::value_error(std::string(name) + " must be a number or have shape (N,)");
        return std::vector<float>(a.data(), a.data() + n);
    };
    const std::vector<float> lo = bound(tmin, "tmin"), hi = bound(tmax, "tmax");
    std::vector<lsnif_ray> rays(n);
    const float* o = origins.data();
    const float* d = directions.data();
    for (std::size_t i = 0; i < n; ++i) {
        for (int a = 0; a < 3; ++a) {
            rays[i].org[a] = o[3 * i + a];
            rays[i].dir[a] = d[3 * i + a];
        }
        rays[i].tmin = lo[i];
        rays[i].tmax = hi[i];
    }
    return rays;
}

// An optional (3, 4) row-major object-to-world matrix.
std::optional<std::vector<float>> make_transform(const py::object& transform) {
    if (transform.is_none()) return std::nullopt;
    FloatArray m = FloatArray::ensure(transform);
    if (!m || m.ndim() != 2 || m.shape(0) != 3 || m.shape(1) != 4)
        throw py::value_error("transform must be a (3, 4) object-to-world matrix");
    return std::vector<float>(m.data(), m.data() + 12);
}

// An enum field as its name, or as the number when this module does not know the value (a
// newer library's).
py::object enum_name(std::uint32_t value, std::initializer_list<const char*> names) {
    if (value < names.size()) return py::str(names.begin()[value]);
    return py::int_(value);
}

// One open asset. close() (also on leaving a `with` block) or garbage collection releases the
// handle. Calls that trace hold it with the GIL released: close() then only marks the model
// closed and the last of them releases it, and the arithmetic cannot change under them
// (lsnif_set_arithmetic must not run concurrently with intersections). The counter is only
// touched with the GIL held.
class Model {
public:
    // `path` as os.fspath gives it: str or bytes.
    explicit Model(const py::object& path) : path_object_(path) {
        const py::module_ os = py::module_::import("os");
        const py::bytes native_bytes = os.attr("fsencode")(path);
        const std::string native = native_bytes;
        // Messages are UTF-8 whatever bytes the name holds (\xff for a byte that is not).
        path_ = native_bytes.attr("decode")("utf-8", "backslashreplace").cast<std::string>();
        lsnif_error e{};
        const lsnif_status status = lsnif_open_file(native.c_str(), &model_, &e);
        if (status != LSNIF_OK) {
            std::string message = path_ + ": " + lsnif_status_string(status);
            if (e.message[0]) message += ": " + std::string(e.message);
            throw Error(message);
        }
    }
    Model(const Model&) = delete;
    Model& operator=(const Model&) = delete;
    // Not reached while a call runs: each holds a reference to the Python object.
    ~Model() { lsnif_close(model_); }

    void close() {
        closed_ = true;
        if (in_flight_ == 0) release();
    }

    const py::object& path() const { return path_object_; }

    const lsnif_model* get() const {
        if (closed_) throw py::value_error(path_ + ": the model is closed");
        return model_;
    }

    py::dict info() const {
        lsnif_info i{};
        check(lsnif_get_info(get(), &i), path_);
        py::dict d;
        d["version_major"] = i.version_major;
        d["version_minor"] = i.version_minor;
        d["grid_resolution"] = i.grid_resolution;
        d["max_points"] = i.max_points;
        d["level_count"] = i.level_count;
        d["features_per_level"] = i.features_per_level;
        d["log2_table_size"] = i.log2_table_size;
        py::list res, entries, dense, hidden;
        for (std::uint32_t l = 0; l < i.level_count && l < LSNIF_MAX_LEVELS; ++l) {
            res.append(i.level_resolution[l]);
            entries.append(i.level_entries[l]);
            dense.append(bool(i.level_dense[l]));
        }
        for (std::uint32_t k = 0; k < i.hidden_layer_count && k < LSNIF_MAX_HIDDEN_LAYERS; ++k)
            hidden.append(i.hidden_width[k]);
        d["level_resolution"] = res;
        d["level_entries"] = entries;
        d["level_dense"] = dense;
        d["hash_primes"] = py::make_tuple(i.hash_primes[0], i.hash_primes[1], i.hash_primes[2]);
        d["input_width"] = i.input_width;
        d["hidden_layer_count"] = i.hidden_layer_count;
        d["hidden_width"] = hidden;
        d["output_count"] = i.output_count;
        d["material_count"] = i.material_count;
        d["activation"] = enum_name(i.activation, {"relu"});
        d["distance_encoding"] = enum_name(i.distance_encoding, {"segment", "first_entry_diagonal"});
        d["box_min"] = py::make_tuple(i.box_min[0], i.box_min[1], i.box_min[2]);
        d["box_max"] = py::make_tuple(i.box_max[0], i.box_max[1], i.box_max[2]);
        d["grid_encoding"] = enum_name(i.grid_encoding, {"fp16", "u8_affine"});
        d["parameter_count"] = i.parameter_count;
        d["occupied_voxels"] = i.occupied_voxels;
        d["file_size"] = i.file_size;
        d["decoded_bytes"] = i.decoded_bytes;
        return d;
    }

    std::uint32_t ray_inputs() const {
        std::uint32_t bits = 0;
        check(lsnif_get_ray_inputs(get(), &bits), path_);
        return bits;
    }

    std::string metadata() const {
        std::size_t n = 0;
        const char* text = lsnif_metadata(get(), &n);
        return std::string(text, n);
    }

    py::object metadata_json() const { return py::module_::import("json").attr("loads")(metadata()); }

    std::string arithmetic() const { return lsnif_arithmetic_string(lsnif_get_arithmetic(get())); }

    void set_arithmetic(const std::string& name) {
        lsnif_arithmetic a;
        if (name == "auto")
            a = LSNIF_ARITHMETIC_AUTO;
        else if (name == "fp32")
            a = LSNIF_ARITHMETIC_FP32;
        else if (name == "bf16")
            a = LSNIF_ARITHMETIC_BF16;
        else if (name == "int8")
            a = LSNIF_ARITHMETIC_INT8;
        else
            throw py::value_error("arithmetic must be auto, fp32, bf16 or int8, not " + name);
        get();  // a closed model raises
        if (in_flight_ != 0)
            throw Error(path_ + ": the arithmetic cannot change while another thread traces this model");
        check(lsnif_set_arithmetic(model_, a, nullptr), path_ + ": lsnif_set_arithmetic");
    }

    std::uint32_t escape_points() const { return lsnif_get_escape_points(get()); }

    void set_escape_points(std::uint32_t limit) {
        get();  // a closed model raises
        if (in_flight_ != 0)
            throw Error(path_ + ": the escape rule cannot change while another thread traces this model");
        if (lsnif_set_escape_points(model_, limit) != LSNIF_OK)
            throw py::value_error("escape_points must be at most the model's max_points, not " +
                                  std::to_string(limit));
    }

    bool enclosed_rule() const { return lsnif_get_enclosed_rule(get()) != 0; }

    void set_enclosed_rule(bool on) {
        get();  // a closed model raises
        if (in_flight_ != 0)
            throw Error(path_ + ": the enclosed rule cannot change while another thread traces this model");
        check(lsnif_set_enclosed_rule(model_, on ? 1 : 0), path_ + ": lsnif_set_enclosed_rule");
    }

    // The occupancy as bool [V][V][V] (z, y, x).
    py::array occupancy() const {
        const lsnif_array a = array(LSNIF_ARRAY_OCCUPANCY, 0);
        const std::size_t V = a.rank == 3 ? std::size_t(a.dims[0]) : 0;
        if (a.dtype != LSNIF_DTYPE_BITS || a.dims[1] != V || a.dims[2] != V || a.bytes < (V * V * V + 7) / 8)
            throw Error(path_ + ": the occupancy array is not V*V*V bits");
        py::array_t<bool> out({V, V, V});
        bool* dst = out.mutable_data();
        const auto* bits = static_cast<const std::uint8_t*>(a.data);
        for (std::size_t i = 0; i < V * V * V; ++i) dst[i] = (bits[i >> 3] >> (i & 7)) & 1u;
        return out;
    }

    // Level l's features: float16 or uint8 [entries][F].
    py::array grid_level(std::uint32_t level) const { return copy(array(LSNIF_ARRAY_GRID_LEVEL, level)); }
    py::array grid_dequant(std::uint32_t level) const {
        lsnif_info i{};
        check(lsnif_get_info(get(), &i), path_);
        if (i.grid_encoding == LSNIF_GRID_FP16)
            throw py::value_error(path_ + ": an fp16 grid has no dequantization pairs");
        return copy(array(LSNIF_ARRAY_GRID_DEQUANT, level));
    }
    py::array layer_weights(std::uint32_t layer) const {
        return copy(array(LSNIF_ARRAY_LAYER_WEIGHTS, layer));
    }
    py::array layer_bias(std::uint32_t layer) const { return copy(array(LSNIF_ARRAY_LAYER_BIAS, layer)); }
    std::uint32_t layer_count() const { return lsnif_layer_count(get()); }

    py::dict intersect(const FloatArray& origins, const FloatArray& directions, const py::object& tmin,
                       const py::object& tmax, const py::object& transform) {
        const std::vector<lsnif_ray> rays = make_rays(origins, directions, tmin, tmax);
        const auto m = make_transform(transform);
        std::vector<lsnif_hit> hits(rays.size());
        lsnif_status status;
        {
            const InFlight trace(*this);
            const lsnif_model* model = trace.model();
            py::gil_scoped_release release;
            status = m ? lsnif_intersect_instance(model, m->data(), rays.data(), rays.size(), hits.data())
                       : lsnif_intersect(model, rays.data(), rays.size(), hits.data());
        }
        check(status, path_ + (m ? ": lsnif_intersect_instance" : ": lsnif_intersect"));
        const std::size_t n = hits.size();
        py::array_t<bool> hit(n);
        py::array_t<float> t(n);
        py::array_t<float> normal({n, std::size_t(3)});
        py::array_t<std::uint32_t> material(n);
        bool* h = hit.mutable_data();
        float* tt = t.mutable_data();
        float* nn = normal.mutable_data();
        std::uint32_t* mm = material.mutable_data();
        for (std::size_t i = 0; i < n; ++i) {
            h[i] = hits[i].hit != 0;
            tt[i] = hits[i].t;
            for (int a = 0; a < 3; ++a) nn[3 * i + a] = hits[i].normal[a];
            mm[i] = hits[i].material;
        }
        py::dict out;
        out["hit"] = hit;
        out["t"] = t;
        out["normal"] = normal;
        out["material"] = material;
        return out;
    }

    py::array occluded(const FloatArray& origins, const FloatArray& directions, const py::object& tmin,
                       const py::object& tmax, const py::object& transform) {
        const std::vector<lsnif_ray> rays = make_rays(origins, directions, tmin, tmax);
        const auto m = make_transform(transform);
        std::vector<std::uint8_t> hit(rays.size());
        lsnif_status status;
        {
            const InFlight trace(*this);
            const lsnif_model* model = trace.model();
            py::gil_scoped_release release;
            status = m ? lsnif_occluded_instance(model, m->data(), rays.data(), rays.size(), hit.data())
                       : lsnif_occluded(model, rays.data(), rays.size(), hit.data());
        }
        check(status, path_ + (m ? ": lsnif_occluded_instance" : ": lsnif_occluded"));
        py::array_t<bool> out(hit.size());
        bool* o = out.mutable_data();
        for (std::size_t i = 0; i < hit.size(); ++i) o[i] = hit[i] != 0;
        return out;
    }

private:
    // A call that uses the handle with the GIL released; constructed and destroyed with the
    // GIL held.
    class InFlight {
    public:
        explicit InFlight(Model& m) : m_(m), model_(m.get()) { ++m_.in_flight_; }
        ~InFlight() {
            if (--m_.in_flight_ == 0 && m_.closed_) m_.release();
        }
        InFlight(const InFlight&) = delete;
        InFlight& operator=(const InFlight&) = delete;
        const lsnif_model* model() const { return model_; }

    private:
        Model& m_;
        const lsnif_model* model_;
    };

    void release() {
        lsnif_close(model_);
        model_ = nullptr;
    }

    lsnif_array array(lsnif_array_kind kind, std::uint32_t index) const {
        lsnif_array a{};
        const lsnif_status s = lsnif_get_array(get(), kind, index, &a);
        if (s == LSNIF_ERR_INVALID_ARGUMENT)
            throw py::index_error(path_ + ": no such array (index " + std::to_string(index) + ")");
        check(s, path_ + ": lsnif_get_array");
        return a;
    }

    // A NumPy copy of an array of bytes, float16 (little-endian, as lsnif_dtype says) or float32
    // (host order) values.
    py::array copy(const lsnif_array& a) const {
        const char* format = a.dtype == LSNIF_DTYPE_UINT8     ? "uint8"
                             : a.dtype == LSNIF_DTYPE_FLOAT16 ? "<f2"
                             : a.dtype == LSNIF_DTYPE_FLOAT32 ? "float32"
                                                              : nullptr;
        if (!format || a.rank < 1 || a.rank > 3)
            throw Error(path_ + ": array of dtype " + std::to_string(a.dtype) + " and rank " +
                        std::to_string(a.rank) + " is not one this module knows");
        const py::dtype dtype(format);
        std::vector<py::ssize_t> shape(a.dims, a.dims + a.rank);
        std::uint64_t count = 1;
        for (const auto d : shape) count *= std::uint64_t(d);
        if (count * std::uint64_t(dtype.itemsize()) != a.bytes)
            throw Error(path_ + ": array of " + std::to_string(a.bytes) + " bytes does not match its shape");
        py::array out(dtype, shape);
        if (a.bytes) std::memcpy(out.mutable_data(), a.data, std::size_t(a.bytes));
        return out;
    }

    py::object path_object_;
    std::string path_;
    lsnif_model* model_ = nullptr;
    bool closed_ = false;
    int in_flight_ = 0;
};

}  // namespace

PYBIND11_MODULE(lsnif, m) {
    m.doc() = "Read LSNIF assets (.lsnif) and trace rays through them with NumPy arrays.";
    py::register_exception<Error>(m, "Error", PyExc_RuntimeError);
    std::uint32_t major = 0, minor = 0;
    const char* version = lsnif_version(&major, &minor);
    m.attr("__version__") = version;
    m.def(
        "version", [] { return std::string(lsnif_version(nullptr, nullptr)); },
        "The linked reader's release, \"MAJOR.MINOR.PATCH\" (lsnif_version).");
    m.attr("container_version") = py::make_tuple(major, minor);
    m.attr("RAY_INPUT_DIRECTION") = std::uint32_t(LSNIF_RAY_INPUT_DIRECTION);
    m.attr("RAY_INPUT_ENTRY_OFFSETS") = std::uint32_t(LSNIF_RAY_INPUT_ENTRY_OFFSETS);
    const float inf = std::numeric_limits<float>::infinity();
    py::class_<Model>(m, "Model", "An open asset. Use lsnif.open(path).")
        .def("close", &Model::close,
             "Releases the asset (once traces running in other threads return); later calls raise "
             "ValueError.")
        .def(
            "__enter__", [](Model& self) -> Model& { return self; }, py::return_value_policy::reference)
        .def("__exit__", [](Model& self, py::args) { self.close(); })
        .def("__repr__",
             [](const Model& self) {
                 return "<lsnif.Model " + py::repr(self.path()).cast<std::string>() + ">";
             })
        .def_property_readonly("path", &Model::path, "The path the asset was opened from.")
        .def_property_readonly("info", &Model::info, "Every field of lsnif_info, as a dict.")
        .def_property_readonly("ray_inputs", &Model::ray_inputs,
                               "Bits of RAY_INPUT_DIRECTION, RAY_INPUT_ENTRY_OFFSETS.")
        .def_property_readonly("metadata", &Model::metadata, "The JSON metadata text.")
        .def_property_readonly("metadata_json", &Model::metadata_json, "The metadata parsed by json.loads.")
        .def_property(
            "arithmetic", &Model::arithmetic, &Model::set_arithmetic,
            "The network's arithmetic in use; set 'auto', 'fp32', 'bf16' or 'int8' (falls back where "
            "the CPU lacks it).")
        .def_property("escape_points", &Model::escape_points, &Model::set_escape_points,
                      "The escape rule's limit (lsnif_set_escape_points): rays starting inside an occupied "
                      "voxel that meet at most this many occupied voxels, each a face neighbour of the one "
                      "before, miss without the network; 0 = off.")
        .def_property(
            "enclosed_rule", &Model::enclosed_rule, &Model::set_enclosed_rule,
            "The enclosed rule (lsnif_set_enclosed_rule): occlusion rays that pass from an occupied "
            "voxel into the empty space the occupied voxels shut in are occluded without the "
            "network; False = off.")
        .def_property_readonly("layer_count", &Model::layer_count)
        .def("occupancy", &Model::occupancy, "bool [V][V][V], indexed [z, y, x].")
        .def("grid_level", &Model::grid_level, py::arg("level"),
             "Level's features [entries][F]: float16, or uint8 for an 8-bit grid (see grid_dequant).")
        .def("grid_dequant", &Model::grid_dequant, py::arg("level"),
             "float32 [2] = (scale, offset) of an 8-bit grid's level: value = fma(q, scale, offset).")
        .def("layer_weights", &Model::layer_weights, py::arg("layer"), "float16 [out][in].")
        .def("layer_bias", &Model::layer_bias, py::arg("layer"), "float16 [out].")
        .def("intersect", &Model::intersect, py::arg("origins"), py::arg("directions"),
             py::arg("tmin") = 0.0f, py::arg("tmax") = inf, py::arg("transform") = py::none(),
             "Closest hits of rays (N, 3) in object space, or in world space with a (3, 4) object-to-world "
             "transform: dict of hit (bool), t (float32), normal (float32 (N, 3)), material (uint32).")
        .def("occluded", &Model::occluded, py::arg("origins"), py::arg("directions"), py::arg("tmin") = 0.0f,
             py::arg("tmax") = inf, py::arg("transform") = py::none(),
             "Whether each ray hits the object within [tmin, tmax]: bool (N,).");
    m.def(
        "open",
        [](const py::object& path) {
            // str, bytes or os.PathLike, as open() takes them.
            return std::make_unique<Model>(py::module_::import("os").attr("fspath")(path));
        },
        py::arg("path"), "Opens and verifies a .lsnif file; lsnif.Error names the file and the problem.");
}
