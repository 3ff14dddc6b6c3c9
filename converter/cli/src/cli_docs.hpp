// The command line described from itself: the README's option tables, the man page and the
// bash completion are all generated from the CLI11 definitions in main.cpp, so none of them
// can drift from what `lsnif` accepts (tests/cli/readme_options.sh, tests/cli/man_completion.sh).
#pragma once

#include <string>

namespace CLI {
class App;
}

namespace lsnif::cli {

// Every subcommand and option as Markdown tables (`lsnif --help-markdown`), for README.md
// "Every command and option".
std::string markdown_reference(const CLI::App& app);

// lsnif(1) in roff (`lsnif --help-man`): every subcommand and option, exit status, files and
// environment. `version` goes into the page's footer; the page carries no date, so the
// same sources give the same bytes.
std::string man_page(const CLI::App& app, const std::string& version);

// A bash completion script for `lsnif` (`lsnif --completion-bash`): subcommands, their
// options, the choices of an option whose value is one of a list ("rays|images|either"),
// and file names where a value is a path.
std::string bash_completion(const CLI::App& app);

}  // namespace lsnif::cli
