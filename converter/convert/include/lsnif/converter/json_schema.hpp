// A small JSON Schema (draft 2020-12) validator for the schemas in schema/.
//
// Debian ships no JSON Schema validator for nlohmann-json, so this implements the subset
// of keywords our schemas use. A schema using any other keyword is rejected when loaded,
// so a schema can never silently rely on something this validator ignores.
// Supported: $schema $id $comment title description $defs $ref(#/$defs/NAME) type enum
// const properties required additionalProperties items minItems maxItems minimum
// maximum exclusiveMinimum exclusiveMaximum minLength maxLength pattern oneOf anyOf.
#pragma once

#include <nlohmann/json.hpp>

#include <string>
#include <vector>

namespace lsnif::converter {

struct SchemaViolation {
    std::string pointer;  // JSON pointer of the offending instance value ("" = root)
    std::string message;
};

class JsonSchema {
public:
    // Parses and checks the schema itself; on failure `error` is set and the object is
    // unusable (valid() == false).
    explicit JsonSchema(const std::string& schema_text);
    bool valid() const { return error_.empty(); }
    const std::string& error() const { return error_; }

    // Every violation, in document order. Empty means the instance conforms.
    std::vector<SchemaViolation> validate(const nlohmann::json& instance) const;

private:
    nlohmann::json root_;
    std::string error_;
};

// The metadata schema of schema/lsnif-metadata.schema.json, embedded at build time.
const std::string& metadata_schema_text();
const JsonSchema& metadata_schema();
// schema/manifest.schema.json, embedded at build time.
const std::string& manifest_schema_text();
const JsonSchema& manifest_schema();
// schema/mesh.LSNIF_neural_geometry.schema.json (the glTF extension), embedded at build time.
const std::string& gltf_extension_schema_text();
const JsonSchema& gltf_extension_schema();

}  // namespace lsnif::converter
