// aggscan report: the QA engineer's reports of one rock or a batch, as HTML
// and PDF, made from the state directory by scripts/report/aggscan_report.py
// (matplotlib plots, WeasyPrint PDF).
#pragma once

#include <iosfwd>
#include <string>
#include <vector>

namespace aggscan {

void PrintReportUsage(std::ostream& o);
/// args: what follows "report". 0 written, 1 the report could not be made
/// (the message says why and what to do), 2 usage, 3 a library is missing.
int RunReportCommand(const std::vector<std::string>& args, std::ostream& out, std::ostream& err);

}  // namespace aggscan
