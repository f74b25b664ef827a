"""Names a user hands the tools (engine.names): one normalisation for names that must not collide, one escape each
for Markdown, CSV and figures; tested here, hard, once; the leaderboard's test checks only that it asks."""

from __future__ import annotations

import csv
import io

import pytest

from engine import names


@pytest.mark.parametrize("lookalike", ["rеference: ray follower",  # a Cyrillic е
                                       "Reference: Ray Follower", "reference:ray_follower", "reference: ray\u00a0follower",
                                       "reference: rαy follower", "ｒｅｆｅｒｅｎｃｅ: ray follower", "réference: ray follower",
                                       "reference˸ ray follower", "ʀeference: ray follower", "reference: rɑy follower",
                                       "reference∶ ray follower"])  # the last four: a hostile trial's, of 35048d1's fix
def test_a_lookalike_of_a_reserved_name_is_refused(lookalike):
    assert names.key(lookalike) == names.key("reference: ray follower")
    problem = names.collision(["SAC", lookalike], reserved=["reference: ray follower"])
    assert "looks like a reserved name, 'reference: ray follower'" in problem


def test_a_name_that_begins_as_the_reserved_ones_do_is_refused():
    assert "begins as the board's own 'reference' names do" in names.collision(
        ["Reference X"], reserved=["reference: oracle"], reserved_start="reference")
    assert names.collision(["reference: oracle", "my referee"], reserved=["reference: oracle"],
                           reserved_start="reference") is None


def test_distinct_names_stand_and_two_that_look_alike_do_not():
    assert names.collision(["SAC, memory", "SAC, hybrid", "TD3", "reference: ray follower"],
                           reserved=["reference: ray follower"]) is None
    assert "looks like another name, 'PPO'" in names.collision(["PPO", "ppo "])


@pytest.mark.parametrize("text,said", [("", "empty"), (" ", "empty"), ("a\nb", "control"), ("a\u200bb", "invisible"),
                                       ("x" * 201, "201 characters")])
def test_what_cannot_be_a_name(text, said):
    assert said in names.check_name(text, "agent")


def test_a_markdown_cell_adds_no_markup():
    cell = names.markdown_cell("| x | ![i](http://e/i.png) **b** <img> $x$ & `c`")
    assert "|" not in cell.replace("\\|", "") and "<" not in cell and "\\!\\[i\\]" in cell and "\\$x\\$" in cell
    cell = names.markdown_cell("sac\n| new row | https://evil.example www.evil.example")
    assert "\n" not in cell and "://" not in cell and "www." not in cell


@pytest.mark.parametrize("text", ["=HYPERLINK(\"http://e\")", "+1+1", "-2+3", "@SUM(A1)", "\tx", "\r=1", "'=1"])
def test_a_csv_cell_is_never_a_formula_and_reads_back_as_written(text):
    cell = names.csv_cell(text)
    assert not cell.startswith(names.FORMULA_START)
    buffer = io.StringIO()
    csv.writer(buffer).writerow([cell])
    (read,) = next(csv.reader(io.StringIO(buffer.getvalue())))
    assert names.csv_name(read) == text


def test_numbers_stay_numbers():
    assert names.csv_cell("-3.5") == "-3.5" and names.csv_cell(-3.5) == -3.5 and names.csv_cell("+1e3") == "+1e3"


def test_a_figure_label_shows_maths_and_underscores_as_written():
    assert names.figure_label("$x_1$") == r"\$x_1\$" and names.figure_label("_hidden") == " _hidden"
