#include "cli_docs.hpp"

#include <CLI/CLI.hpp>

#include <cctype>
#include <string>
#include <vector>

namespace lsnif::cli {
namespace {

// One option as its documentation shows it, read from its CLI11 definition.
struct OptionDoc {
    std::vector<std::string> names;  // "--preset", "-o", or the positional's name
    std::string value;               // the value's name ("FILE", "rays|images|either"); empty: a flag
    std::string fallback;            // the default in words; empty: none worth showing
    std::string what;                // the help text, without its default
    bool required = false;
    bool positional = false;
};

// The subcommands of `app` in the order they were added.
std::vector<const CLI::App*> subcommands(const CLI::App& app) {
    return app.get_subcommands([](const CLI::App*) { return true; });
}

OptionDoc describe(const CLI::Option& o) {
    OptionDoc d;
    d.positional = !o.nonpositional();
    if (d.positional) d.names.push_back(o.get_name(true, false));
    for (const std::string& s : o.get_snames()) d.names.push_back("-" + s);
    for (const std::string& l : o.get_lnames()) d.names.push_back("--" + l);
    d.what = o.get_description();
    d.fallback = o.get_default_str();
    // Settings-table rows carry their default in words at the end of their help.
    const std::size_t tail = d.what.rfind(" [default: ");
    if (tail != std::string::npos && d.what.back() == ']') {
        d.fallback = d.what.substr(tail + 11, d.what.size() - tail - 12);
        d.what.resize(tail);
    }
    if (d.fallback == "[]") d.fallback.clear();
    // The value's name, without CLI11's description of its range check ("N:INT in [0 - 4096]").
    const std::string type = o.get_type_name();
    d.value = type.substr(0, type.find(':'));
    if (o.get_expected_min() == 0) d.value.clear();
    d.required = o.get_required();
    return d;
}

// The documented options of `sub`: --help is CLI11's own and said once for all.
std::vector<OptionDoc> options_of(const CLI::App& sub) {
    std::vector<OptionDoc> out;
    for (const CLI::Option* o : sub.get_options()) {
        OptionDoc d = describe(*o);
        if (d.names.size() == 2 && d.names[0] == "-h" && d.names[1] == "--help") continue;
        out.push_back(std::move(d));
    }
    return out;
}

std::string joined(const std::vector<std::string>& parts, const std::string& separator) {
    std::string out;
    for (const std::string& p : parts) out += (out.empty() ? "" : separator) + p;
    return out;
}

// ---- Markdown ----

// "a | b" as a Markdown table cell: pipes escaped, one line.
std::string cell(const std::string& text) {
    std::string out;
    for (char c : text) {
        if (c == '|') out += '\\';
        out += c == '\n' ? ' ' : c;
    }
    return out;
}

void markdown_options(const CLI::App& sub, const std::string& path, std::string& out) {
    out += "### `" + path + "`\n\n" + sub.get_description() + "\n\n";
    out += "| option | value | default | what it does |\n|---|---|---|---|\n";
    for (const OptionDoc& d : options_of(sub)) {
        const std::string def = d.required ? "required" : d.fallback.empty() ? "" : "`" + d.fallback + "`";
        out += "| `" + cell(joined(d.names, ",")) + "` | " + cell(d.value) + " | " + cell(def) + " | " +
               cell(d.what) + " |\n";
    }
    out += "\n";
    for (const CLI::App* nested : subcommands(sub))
        markdown_options(*nested, path + " " + nested->get_name(), out);
}

// ---- roff (man(7)) ----

// Text safe in a roff line: backslashes and hyphens escaped, and a line that would start with
// a control character ('.' or '\'') guarded by the zero-width \&.
std::string roff(const std::string& text) {
    std::string out;
    for (char c : text) {
        if (c == '\\')
            out += "\\e";
        else if (c == '-')
            out += "\\-";
        else if (c == '\n')
            out += ' ';
        else
            out += c;
    }
    if (!out.empty() && (out[0] == '.' || out[0] == '\'')) out = "\\&" + out;
    return out;
}

void man_options(const CLI::App& sub, const std::string& path, std::string& out) {
    out += ".SS \"" + roff(path) + "\"\n" + roff(sub.get_description()) + "\n";
    for (const OptionDoc& d : options_of(sub)) {
        out += ".TP\n";
        std::vector<std::string> names;
        for (const std::string& n : d.names) names.push_back("\\fB" + roff(n) + "\\fR");
        out += joined(names, ", ");
        if (!d.value.empty() && !d.positional) out += " \\fI" + roff(d.value) + "\\fR";
        out += "\n" + roff(d.what);
        if (d.required)
            out += " (required)";
        else if (!d.fallback.empty())
            out += " (default: " + roff(d.fallback) + ")";
        out += "\n";
    }
    for (const CLI::App* nested : subcommands(sub))
        man_options(*nested, path + " " + nested->get_name(), out);
}

// ---- bash ----

// A word list as a single-quoted bash string (option names and choices hold no quotes).
std::string quoted(const std::vector<std::string>& words) {
    return "'" + joined(words, " ") + "'";
}

// The value names whose values are paths: bash offers file names for them.
bool names_a_path(const std::string& value) {
    for (const char* p : {"FILE", "DIR", "PATH"})
        if (value.rfind(p, 0) == 0) return true;
    return false;
}

// A value named by its choices ("rays|images|either"), not by placeholders ("DIR|URL").
bool is_choice_list(const std::string& value) {
    if (value.find('|') == std::string::npos) return false;
    for (char c : value)
        if (!(std::islower(static_cast<unsigned char>(c)) || std::isdigit(static_cast<unsigned char>(c)) ||
              c == '|'))
            return false;
    return true;
}

// One `case` arm per subcommand path ("convert", "bench infer"): what may follow a word.
void bash_arms(const CLI::App& sub, const std::string& path, std::string& out) {
    std::vector<std::string> words, nested;
    std::string value_arms;
    for (const OptionDoc& d : options_of(sub)) {
        if (d.positional) continue;
        for (const std::string& n : d.names) words.push_back(n);
        if (d.value.empty()) continue;
        std::string reply;
        if (names_a_path(d.value)) {
            reply = "COMPREPLY=($(compgen -f -- \"$cur\"))";
        } else if (is_choice_list(d.value)) {
            std::string choices = d.value;
            for (char& c : choices)
                if (c == '|') c = ' ';
            reply = "COMPREPLY=($(compgen -W '" + choices + "' -- \"$cur\"))";
        } else {
            reply = "COMPREPLY=()";
        }
        value_arms += "                " + joined(d.names, "|") + ") " + reply + "; return ;;\n";
    }
    for (const CLI::App* n : subcommands(sub)) nested.push_back(n->get_name());
    words.push_back("--help");
    out += "        '" + path + "')\n            case \"$prev\" in\n" + value_arms + "            esac\n";
    out += "            if [[ $cur == -* ]]; then\n                COMPREPLY=($(compgen -W " + quoted(words) +
           " -- \"$cur\"))\n";
    if (!nested.empty())
        out += "            else\n                COMPREPLY=($(compgen -W " + quoted(nested) +
               " -- \"$cur\"))\n";
    else
        out += "            else\n                COMPREPLY=($(compgen -f -- \"$cur\"))\n";
    out += "            fi ;;\n";
    for (const CLI::App* n : subcommands(sub)) bash_arms(*n, path + " " + n->get_name(), out);
}

// The subcommand path a command line has reached: the words that name subcommands, in order,
// from the top (`lsnif bench infer --steps 3` is at "bench infer").
void bash_paths(const CLI::App& app, const std::string& path, std::string& out) {
    for (const CLI::App* n : subcommands(app)) {
        const std::string full = path.empty() ? n->get_name() : path + " " + n->get_name();
        out += "            '" + path + "/" + n->get_name() + "') path='" + full + "'; continue ;;\n";
        bash_paths(*n, full, out);
    }
}

}  // namespace

std::string markdown_reference(const CLI::App& app) {
    std::string out;
    for (const CLI::App* sub : subcommands(app)) markdown_options(*sub, "lsnif " + sub->get_name(), out);
    return out;
}

std::string man_page(const CLI::App& app, const std::string& version) {
    std::vector<std::string> names;
    for (const CLI::App* sub : subcommands(app)) names.push_back(sub->get_name());
    std::string out;
    out += ".TH LSNIF 1 \"\" \"lsnif " + roff(version) + "\" \"User Commands\"\n";
    out += ".SH NAME\nlsnif \\- " + roff(app.get_description().substr(app.get_description().find(": ") + 2)) +
           "\n";
    out +=
        ".SH SYNOPSIS\n.B lsnif\n\\fICOMMAND\\fR [\\fIOPTIONS\\fR] [\\fIINPUTS\\fR]\n.br\n.B lsnif\n"
        "[\\fB\\-\\-version\\fR | \\fB\\-\\-help\\fR | \\fB\\-\\-help\\-markdown\\fR | "
        "\\fB\\-\\-help\\-man\\fR | \\fB\\-\\-completion\\-bash\\fR]\n"
        ".PP\n\\fICOMMAND\\fR is one of " +
        roff(joined(names, ", ")) + ".\n";
    out +=
        ".SH DESCRIPTION\n"
        "LSNIF assets are small neural networks that stand in for the bottom-level BVH of "
        "geometrically complex objects: a renderer traces secondary rays against them at a "
        "fraction of the memory.\n"
        ".B lsnif convert\nturns a scene (glTF, OBJ, PLY, STL, OFF) into assets, a manifest and a report;\n"
        ".B lsnif batch\nconverts an asset library with a shared cache, in shards or one task per object;\n"
        ".B lsnif eval\nrenders a converted scene against Embree and measures the difference;\n"
        ".B lsnif inspect\nand\n.B lsnif validate\nread and check single assets;\n"
        ".B lsnif bench\nmeasures training, inference, memory and ray throughput.\n"
        "Every option below is also listed by\n.BR \"lsnif COMMAND \\-\\-help\" .\n";
    out += ".SH COMMANDS\n";
    for (const CLI::App* sub : subcommands(app)) man_options(*sub, "lsnif " + sub->get_name(), out);
    out +=
        ".SH EXIT STATUS\n"
        ".TP\n.B 0\nSuccess: every asset converted, or rightly kept as a BVH.\n"
        ".TP\n.B 1\nAn input or an asset failed; the others were still converted.\n"
        ".TP\n.B 2\nUsage: a bad or missing option, or a setting no conversion can meet.\n";
    out +=
        ".SH ENVIRONMENT\n"
        ".TP\n.B LSNIF_CACHE_TOKEN\nThe bearer token sent to a cache server given with "
        "\\fB\\-\\-cache\\fR \\fIURL\\fR (never on the command line, where other users see it).\n"
        ".TP\n.B LSNIF_ISA\nCaps the instruction sets the kernels may use: generic, avx2, avx512, "
        "avx512bf16 or amx.\n";
    out +=
        ".SH FILES\n"
        ".TP\n.I OUT/manifest.json\nWhat each object became and why (schema lsnif\\-manifest).\n"
        ".TP\n.I OUT/*.lsnif\nThe assets, named by their content; a renderer's reader opens them.\n"
        ".TP\n.I OUT/scene.gltf\nThe scene again, each converted mesh replaced by a reference to "
        "its asset.\n"
        ".TP\n.I OUT/report.html\nThe report \\fBscripts/convert\\-scene\\fR writes: objects, "
        "accuracy, memory, renders and close\\-ups.\n";
    out +=
        ".SH SEE ALSO\n"
        "The project's README.md, docs/pipeline.md (batch conversion, caches, schedulers) and "
        "docs/model.md (what an asset is and how it is accepted).\n";
    return out;
}

std::string bash_completion(const CLI::App& app) {
    std::vector<std::string> top;
    for (const CLI::App* sub : subcommands(app)) top.push_back(sub->get_name());
    for (const char* flag : {"--version", "--help", "--help-markdown", "--help-man", "--completion-bash"})
        top.push_back(flag);
    std::string out =
        "# bash completion for lsnif, generated by `lsnif --completion-bash`.\n"
        "_lsnif() {\n"
        "    local cur=${COMP_WORDS[COMP_CWORD]} prev=${COMP_WORDS[COMP_CWORD-1]} path='' word i\n"
        "    for ((i = 1; i < COMP_CWORD; ++i)); do\n"
        "        word=${COMP_WORDS[i]}\n"
        "        case \"$path/$word\" in\n";
    bash_paths(app, "", out);
    out +=
        "        esac\n"
        "    done\n"
        "    case \"$path\" in\n"
        "        '')\n"
        "            COMPREPLY=($(compgen -W " +
        quoted(top) + " -- \"$cur\")) ;;\n";
    for (const CLI::App* sub : subcommands(app)) bash_arms(*sub, sub->get_name(), out);
    out +=
        "    esac\n"
        "}\n"
        "complete -o filenames -F _lsnif lsnif\n";
    return out;
}

}  // namespace lsnif::cli
