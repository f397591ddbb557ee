// `aggscan user`: the accounts of the API (daemon/access.h), kept in the file
// named by daemon.credentials_file. aggscand rereads it when it changes.
//
//   aggscan user add NAME --role operator|viewer --file FILE
//       the password is read from the terminal (twice, not shown) or, when
//       stdin is not a terminal, as its first line; replaces NAME's entry
//   aggscan user remove NAME --file FILE
//   aggscan user list --file FILE
#pragma once

#include <istream>
#include <ostream>
#include <string>
#include <vector>

namespace aggscan {

int RunUserCommand(const std::vector<std::string>& args, std::istream& in, std::ostream& out,
                   std::ostream& err);
void PrintUserUsage(std::ostream& o);

}  // namespace aggscan
