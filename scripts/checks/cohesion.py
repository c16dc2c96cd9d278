#!/usr/bin/env python3
"""Cohesion rules of the house style, read from the Rust sources of every crate in the workspace:

1. No import cycle among sibling modules. Module `a::x` uses `a::y` when any file of `a::x`
   (its own file or a descendant's) names a path into `a::y` (`super::y::..`, `crate::a::y::..`,
   or an item the parent `a` re-exports from `y`). Two siblings that use each other, directly or
   through other siblings, are a cycle: the concern was cut through the middle.
2. One type's inherent `impl` blocks live in one file, so a reader finds all of a type's methods
   in one place (trait impls may live beside the trait or the caller). A type may keep them in
   several files with a reason: a comment containing `shape:` in the three lines above its
   `struct` or `enum`, which says where they are and why.

Only non-test code counts (a file's trailing `#[cfg(test)] mod` and `*_tests.rs` files are
skipped). scripts/checks/shape.py runs these checks; run alone, this prints what it finds.

Usage: python3 scripts/checks/cohesion.py [DIR ...]
"""
import os
import re
import sys

USE_RE = re.compile(r'^\s*(?:pub(?:\([^)]*\))?\s+)?use\s+([^;]+);', re.M | re.S)
PATH_RE = re.compile(r'\b((?:crate|super|self)(?:::\w+)+)')
MOD_RE = re.compile(r'^(#\[cfg\(test\)\]\s*)?\s*(?:pub(?:\([^)]*\))?\s+)?mod\s+(\w+)\s*;', re.M)
# Comments and literals, in one pass so that a quote in a comment or `//` in a string is not
# mistaken for the other: line comment, block comment, raw string, string, char literal.
TOKEN_RE = re.compile(r'//[^\n]*|/\*[\s\S]*?\*/|r(#*)"[\s\S]*?"\1|"(?:\\[\s\S]|[^"\\])*"'
                      r"|'(?:\\[\s\S][^']*|[^'\\])'")
IMPL_RE = re.compile(r'^impl(?:<[^{]*?>)?\s+([A-Z]\w*)(?:<[^{]*?>)?\s*(?:where[^{]*)?\{', re.M)


def non_test_lines(lines):
    """The lines before a top-level `#[cfg(test)] mod ... {` (scripts/checks/shape.py counts these too)."""
    for i, line in enumerate(lines[:-1]):
        if line.startswith('#[cfg(test)]') and re.match(r'(pub )?mod \w+ \{', lines[i + 1]):
            return lines[:i]
    return lines


def strip(text):
    """The text without comments, string literals and the trailing test module."""
    code = '\n'.join(non_test_lines(text.split('\n')))
    return TOKEN_RE.sub(lambda m: '""' if m.group(0).endswith('"') else ' ', code)


def expand(tree):
    """`a::{b, c::{d, e}}` -> ['a::b', 'a::c::d', 'a::c::e'] (renames and globs dropped)."""
    tree = re.sub(r'\s+', '', re.sub(r'\s+as\s+\w+', '', tree))
    depth, start = 0, tree.find('{')
    if start < 0:
        return [tree]
    prefix, inner = tree[:start], tree[start + 1:tree.rfind('}')]
    parts, buf = [], ''
    for ch in inner:
        depth += ch == '{'
        depth -= ch == '}'
        if ch == ',' and depth == 0:
            parts.append(buf)
            buf = ''
        else:
            buf += ch
    parts.append(buf)
    out = []
    for p in filter(None, parts):
        out += [prefix + q for q in expand(p)]
    return out


class Crate:
    """One crate's module tree: module path (tuple) -> its files, what it names, what it re-exports."""

    def __init__(self, src):
        self.src = src
        self.files = {}      # module -> [file]
        self.names = {}      # module -> [(absolute path, file)]
        self.exports = {}    # module -> {name: absolute path}
        for root in ('lib.rs', 'main.rs'):
            if os.path.exists(os.path.join(src, root)):
                self.load((), os.path.join(src, root))
        raw, self.names = self.names, {}
        for module, names in raw.items():
            resolved = self.names.setdefault(module, [])
            for segments, path, public in names:
                absolute = self.resolve(module, segments)
                if absolute:
                    resolved.append((absolute, path))
                    if public and absolute[-1] not in ('*', 'self'):
                        self.exports[module][absolute[-1]] = absolute

    def load(self, module, path):
        with open(path, encoding='utf-8') as f:
            text = strip(f.read())
        self.files.setdefault(module, []).append(path)
        names = self.names.setdefault(module, [])
        exports = self.exports.setdefault(module, {})
        for m in USE_RE.finditer(text):
            public = m.group(0).lstrip().startswith('pub')
            for used in expand(m.group(1)):
                names.append((used.split('::'), path, public))
        for m in PATH_RE.finditer(USE_RE.sub('', text)):
            names.append((m.group(1).split('::'), path, False))
        here = os.path.dirname(path)
        base = os.path.basename(path)
        child_dir = here if base in ('lib.rs', 'main.rs', 'mod.rs') else os.path.join(here, base[:-3])
        for m in MOD_RE.finditer(text):
            if m.group(1):
                continue  # a test module
            name = m.group(2)
            for candidate in (os.path.join(child_dir, name + '.rs'),
                              os.path.join(child_dir, name, 'mod.rs')):
                if os.path.exists(candidate) and not candidate.endswith('_tests.rs'):
                    self.load(module + (name,), candidate)
                    break

    def resolve(self, module, segments):
        """An absolute path for `segments` named inside `module`; None outside this crate."""
        if not segments or segments[0] not in ('crate', 'super', 'self'):
            if segments and module + (segments[0],) in self.files:
                return module + tuple(segments)
            return None
        base = list(module)
        if segments[0] == 'crate':
            base, segments = [], segments[1:]
        while segments and segments[0] in ('super', 'self'):
            if segments[0] == 'super' and base:
                base.pop()
            segments = segments[1:]
        return tuple(base + segments)

    def target(self, path, seen=0):
        """The module that defines what `path` names, following re-exports."""
        for n in range(len(path), -1, -1):
            if path[:n] in self.files:
                module = path[:n]
                rest = path[n:]
                if rest and seen < 8 and rest[0] in self.exports.get(module, {}):
                    via = self.exports[module][rest[0]]
                    if via[:len(module)] == module and len(via) > len(module) + 1:
                        return self.target(via + rest[1:], seen + 1)
                return module
        return ()


def cycles(crate):
    """Sibling-module cycles: [(parent, [members], [example uses])]."""
    edges = {}  # parent -> {child: {child: (file, path)}}
    for module, names in crate.names.items():
        for path, file in names:
            target = crate.target(path)
            common = 0
            while common < min(len(module), len(target)) and module[common] == target[common]:
                common += 1
            if common >= len(module) or common >= len(target):
                continue  # an ancestor or a descendant, not a sibling
            parent = module[:common]
            a, b = module[common], target[common]
            edges.setdefault(parent, {}).setdefault(a, {}).setdefault(b, (file, '::'.join(path)))
    found = []
    for parent, graph in sorted(edges.items()):
        for component in strongly_connected(graph):
            if len(component) > 1:
                examples = [f'{a} -> {b} ({graph[a][b][0]}: {graph[a][b][1]})'
                            for a in sorted(component) for b in sorted(graph.get(a, {}))
                            if b in component]
                found.append((parent, sorted(component), examples))
    return found


def strongly_connected(graph):
    """Tarjan's algorithm over a small dict-of-dicts graph."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, {}):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            out.append(component)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def split_impls(crate):
    """Types whose inherent impl blocks are spread over several files: [(module, type, [files])].
    A type is known by the module that defines it: its own file's, or where its `use` leads."""
    where = {}
    for module, files in crate.files.items():
        for path in files:
            with open(path, encoding='utf-8') as f:
                text = strip(f.read())
            imported = {}
            for m in USE_RE.finditer(text):
                for used in expand(m.group(1)):
                    absolute = crate.resolve(module, used.split('::'))
                    if absolute:
                        imported[absolute[-1]] = crate.target(absolute)
            for name in IMPL_RE.findall(text):
                where.setdefault((imported.get(name, module), name), set()).add(path)
    return [(module, name, sorted(paths)) for (module, name), paths in sorted(where.items())
            if len(paths) > 1]


def spread_reason(crate, module, name):
    """Whether type `name` of `module` says why its impl is spread: `shape:` in a comment within
    the three lines above its `struct` or `enum`."""
    definition = re.compile(r'^\s*(?:pub(?:\([^)]*\))?\s+)?(?:struct|enum)\s+' + re.escape(name)
                            + r'\b')
    for path in crate.files.get(module, []):
        with open(path, encoding='utf-8') as f:
            lines = f.read().split('\n')
        for i, line in enumerate(lines):
            if definition.match(line):
                return any('shape:' in above for above in lines[max(0, i - 3):i])
    return False


def crates(roots):
    for root in roots:
        for d, dirs, files in os.walk(root):
            dirs[:] = sorted(x for x in dirs if x not in ('target', '.git', 'node_modules'))
            if 'Cargo.toml' in files and os.path.isdir(os.path.join(d, 'src')):
                yield Crate(os.path.join(d, 'src'))


def findings(roots):
    found = []
    for crate in crates(roots):
        for parent, members, examples in cycles(crate):
            where = '::'.join(('crate',) + parent)
            found.append(f'cycle in {crate.src} {where}: {" <-> ".join(members)}\n    '
                         + '\n    '.join(examples))
        for module, name, paths in split_impls(crate):
            spread = f'impl {name} spread over {len(paths)} files: {", ".join(paths)}'
            if spread_reason(crate, module, name):
                found.append('note: ' + spread + ' (with a reason)')
            else:
                found.append(spread)
    return found


def self_test():
    """The checker on a made-up crate: a cycle through a re-export and a `use` group is found,
    a child using its parent is not a cycle, a test module does not count, two impls of one
    type in two files are listed, as a note when the type gives a reason."""
    import tempfile
    with tempfile.TemporaryDirectory() as root:
        files = {
            'Cargo.toml': '',
            'src/lib.rs': 'pub mod a;\npub mod b;\npub mod c;\npub mod d;\n#[cfg(test)]\nmod tests;\n',
            'src/a/mod.rs': 'mod x;\nmod y;\npub use self::y::Thing;\npub struct A;\n',
            'src/a/x.rs': 'use super::{Thing, A};\nimpl A { fn f() {} }\n',
            'src/a/y.rs': 'pub struct Thing;\nuse super::x as _; // super::x here\n'
                          'fn g() { let s = "crate::c::C"; super::x::h(); }\n',
            'src/b.rs': 'use crate::a::A;\nimpl A { fn k() {} }\n',
            'src/c.rs': '// shape: its methods by concern, here and in d.rs\npub struct C;\n'
                        'impl C { fn m() {} }\n',
            'src/d.rs': 'use crate::c::C;\nimpl C { fn n() {} }\n',
            'src/tests.rs': 'use crate::{a, b, c};\n',
        }
        for name, text in files.items():
            os.makedirs(os.path.dirname(os.path.join(root, name)), exist_ok=True)
            with open(os.path.join(root, name), 'w', encoding='utf-8') as f:
                f.write(text)
        found = findings([root])
    cycles_found = [f for f in found if f.startswith('cycle')]
    assert len(cycles_found) == 1 and 'crate::a: x <-> y' in cycles_found[0], found
    assert any(f.startswith('impl A spread over 2 files') for f in found), found
    assert any(f.startswith('note: impl C spread over 2 files') for f in found), found
    assert len(found) == 3, found


if __name__ == '__main__':
    if '--self-test' in sys.argv:
        self_test()
        print('cohesion: self-test passed')
        sys.exit(0)
    result = findings([a for a in sys.argv[1:] if not a.startswith('--')] or ['.'])
    print('\n'.join(result) if result else 'cohesion: no sibling cycle, no type spread over files')
    sys.exit(1 if any(not r.startswith('note: ') for r in result) and '--check' in sys.argv else 0)
