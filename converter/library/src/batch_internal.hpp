// What `lsnif batch` (batch.cpp), its plan files (batch_plan.cpp) and its Ninja file
// (batch_ninja.cpp) share. Private to lsnif::library.
#pragma once

#include <lsnif/library/batch.hpp>

#include <optional>
#include <string>
#include <vector>

namespace lsnif::library::detail {

// One unique candidate of a library's plan: what one task (a Ninja edge, a --task) converts.
struct PlannedObject {
    std::string key, source, mesh;  // source: the scene file, absolute
    std::size_t input = 0;          // index into the planned scenes
    std::uint64_t estimated_ms = 0;
};

// The path made absolute and normal (as keys record sources), or `p` when it cannot be.
std::string absolute(const std::string& p);
// A word for /bin/sh, single-quoted unless it needs no quoting; a line of such words.
std::string shell_word(const std::string& w);
std::string shell_line(const std::vector<std::string>& words);

// Plans the library r.scenes (made absolute, since a source path is part of each key) with
// the settings of `c` (a dry run): its unique candidates, costliest first, ties by key. None
// (r.exit set) when the options are refused.
std::optional<std::vector<PlannedObject>> plan_library(converter::ConvertOptions c,
                                                       const converter::ConvertProgress& progress,
                                                       BatchResult& r);

// Converts the library r.scenes with the settings of `c` (its inputs are set here): every
// asset's line, the counts, the summary, the JUnit file of `options`, the exit code.
void convert_library(const BatchOptions& options, converter::ConvertOptions c,
                     const converter::ConvertProgress& progress,
                     const std::function<void(const std::string&)>& on_line, BatchResult& r);

// Records `error` among the conversion's errors and sets the exit code.
void fail(BatchResult& r, const std::string& error, BatchExit exit = BatchExit::failed);
// A plan written (--ninja, --plan): the inputs' and the conversion's errors become warnings
// "(the STEP will fail on it)", since that step is where CI sees them, and the run exits ok.
void defer_errors(BatchResult& r, const std::string& step);

// --ninja FILE (batch_ninja.cpp): plans the library r.scenes and writes the Ninja file and
// its depfile atomically; r.exit and the errors say how it went.
void plan_ninja(const BatchOptions& options, const converter::ConvertProgress& progress, BatchResult& r);

// --plan FILE and --from-plan FILE (batch_plan.cpp).
void write_plan(const BatchOptions& options, const converter::ConvertProgress& progress, BatchResult& r);
void run_from_plan(const BatchOptions& options, const converter::ConvertProgress& progress,
                   const std::function<void(const std::string&)>& on_line, BatchResult& r);

}  // namespace lsnif::library::detail
