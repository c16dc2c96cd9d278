#!/usr/bin/env python3
"""Keeps the code in rooms cut by concern: lists non-test Rust functions longer than --fn lines,
modules with more than --mod non-test, non-comment lines, and (scripts/checks/cohesion.py) import
cycles among sibling modules. A function or module may stay larger with a reason: a comment
containing `shape:` in the three lines above the `fn`, or in the first five lines of the module.
No cycle may stay, and a type's inherent impl stays in one file unless the type gives a reason
(scripts/checks/cohesion.py says how); types that give one are listed as notes.
With --check it exits 1 when anything but a note is listed (scripts/test.sh runs it).

Usage: python3 scripts/checks/shape.py [--check] [--fn 80] [--mod 400] [DIR ...]
"""
import os
import re
import sys

import cohesion
from cohesion import non_test_lines

FN_RE = re.compile(r'^(\s*)(pub(\([^)]*\))? )?(async )?(const )?(unsafe )?fn (\w+)')


def arg(name, default):
    return int(sys.argv[sys.argv.index(name) + 1]) if name in sys.argv else default


def rust_files(roots):
    for root in roots:
        for d, dirs, files in os.walk(root):
            # Build output, and integration tests (tests/tests), are not product code.
            dirs[:] = sorted(x for x in dirs if x not in ('target', '.git', 'node_modules')
                             and not (x == 'tests' and os.path.basename(d) == 'tests'))
            for f in sorted(files):
                if f.endswith('.rs') and f != 'tests.rs' and not f.endswith('_tests.rs'):
                    yield os.path.join(d, f)


def long_functions(lines, limit):
    i = 0
    while i < len(lines):
        m = FN_RE.match(lines[i])
        if not m:
            i += 1
            continue
        indent, start = len(m.group(1)), i
        j = i
        while j < len(lines) and not lines[j].rstrip().endswith(('{', ';')):
            j += 1
        if j < len(lines) and lines[j].rstrip().endswith(';'):
            i = j + 1  # a declaration without a body
            continue
        k = j + 1
        while k < len(lines) and not (lines[k].startswith(' ' * indent + '}')
                                      and len(lines[k]) - len(lines[k].lstrip()) == indent):
            k += 1
        length = k - start + 1
        reason = 'shape:' in ' '.join(lines[max(0, start - 3):start])
        if length > limit and not reason:
            yield length, start + 1, m.group(7)
        i = start + 1


def main():
    fn_max, mod_max = arg('--fn', 80), arg('--mod', 400)
    skip = {str(fn_max), str(mod_max)}
    roots = [a for a in sys.argv[1:] if not a.startswith('--') and a not in skip] or ['.']
    found = []
    for path in rust_files(roots):
        with open(path, encoding='utf-8') as f:
            lines = non_test_lines(f.read().split('\n'))
        code = [l for l in lines if l.strip() and not l.strip().startswith('//')]
        if len(code) > mod_max and not any('shape:' in l for l in lines[:5]):
            found.append(f'module {path}: {len(code)} non-test lines (limit {mod_max})')
        for length, line, name in long_functions(lines, fn_max):
            found.append(f'fn {path}:{line} {name}: {length} lines (limit {fn_max})')
    if '--check' in sys.argv:
        cohesion.self_test()
    notes = []
    for finding in cohesion.findings(roots):
        (notes if finding.startswith('note: ') else found).append(finding)
    if notes:
        print('\n'.join(notes))
    print('\n'.join(found) if found else
          f'shape: no fn over {fn_max} lines, no module over {mod_max}, no sibling import cycle, '
          'no type spread over files without a reason')
    return 1 if found and '--check' in sys.argv else 0


if __name__ == '__main__':
    sys.exit(main())
