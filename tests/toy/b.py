"""Toy stage b."""

from panoworld.framework.stage import Input
from tests.toy.common import entry, main_of, make_stage

globals().update(make_stage("b", {"a": Input("toy")}))
main = main_of(__name__)

if __name__ == "__main__":
    entry(__name__)
